"""How much does the video see of a reconstruction's worst patch?

    python docs/analysis/worst_patch_parallax.py [run_root=outputs] [folds=0,1,2,3] [threshold_mm=1.5]

For each held-out patient of a ``benchmarks/paper_table.py`` run: the ``full`` mesh's vertices are registered
to the patient's CT with the Sim(3) its evaluation found, and the vertices farther than ``threshold_mm`` from
the CT (else the worst 1 %) are the *worst patch*.  Two numbers say whether any multi-view check could see it:

* **parallax**: for frames i and i + k that both see a vertex, how far apart (pixels, at 256x320) the vertex and
  its closest CT point move between the two views, relative to each other: the image evidence that tells the
  reconstructed surface from the true one.  Under ~1 px no photometric or flow check separates them.
  Divided by the vertex's error (vertices off by more than 0.2 mm): how visible an error there is at all.
* **photo-consistency**: the normalised cross-correlation (7x7 px) of frame i with frame i + 8 warped into it
  through the mesh's rendered depth, averaged per vertex: higher = the mesh explains the two views better.

Ground truth (CT, the evaluation's registration) is read here only to pick the worst patch.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from endorecon.data.dataset import load_ground_truth  # noqa: E402
from endorecon.data.sequence import Sequence, read_poses_txt  # noqa: E402
from endorecon.data.transforms import resize_sequence  # noqa: E402
from endorecon.evaluation.meshes import ReferenceSurface, load_mesh  # noqa: E402
from endorecon.rendering.raycast import MeshRenderer, load_mesh_arrays  # noqa: E402

HW = (256, 320)


def project(X: np.ndarray, T: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return Xc[:, :2] / Xc[:, 2:3] * np.diag(K)[:2] + K[:2, 2], Xc[:, 2]


def box(x: torch.Tensor, k: int) -> torch.Tensor:
    return F.avg_pool2d(x[None, None], k, 1, k // 2, count_include_pad=False)[0, 0]


def ncc(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor, k: int = 7) -> tuple[torch.Tensor, torch.Tensor]:
    w = valid.float()
    sw = box(w, k).clamp_min(1e-6)
    ma, mb = box(a * w, k) / sw, box(b * w, k) / sw
    va, vb = box(a * a * w, k) / sw - ma**2, box(b * b * w, k) / sw - mb**2
    out = (box(a * b * w, k) / sw - ma * mb) / torch.sqrt(va.clamp_min(1e-8) * vb.clamp_min(1e-8))
    return out, valid & (sw > 0.8) & (va > 1e-5) & (vb > 1e-5)


def analyse(run_root: Path, fold: int, threshold_mm: float) -> dict:
    name = f"patient_{fold:02d}__seq_00"
    last = sorted((run_root / "train" / f"fold={fold}").glob("iteration=*"), key=lambda p: int(p.name.split("=")[1]))[-1]
    seq_dir = last / "sequences" / name
    metrics = json.loads((run_root / "benchmarks" / "paper_table" / f"fold={fold}" / "full" / name / "evaluation"
                          / "metrics.json").read_text())
    S = np.array(metrics["sim3"]["matrix"])
    cache = next((run_root / "cache" / "sfm").glob(f"*/{name}/sequence.npz"), None)
    if cache is None:  # a run with its own output root but the shared SfM cache
        cache = next((ROOT / "outputs" / "cache" / "sfm").glob(f"*/{name}/sequence.npz"))
    seq = Sequence.load(cache)
    seq = resize_sequence(seq, *HW) if (seq.height, seq.width) != HW else seq
    _, poses = read_poses_txt(seq_dir / "poses.txt")
    V, T = load_mesh_arrays(str(seq_dir / "mesh.ply"))
    data = run_root / "data" / "phantom" if (run_root / "data" / "phantom").is_dir() else ROOT / "outputs" / "data" / "phantom"
    ref = ReferenceSurface(load_mesh(load_ground_truth(data, fold).mesh_path))
    V_ct = V @ S[:3, :3].T + S[:3, 3]
    res = ref.distance(V_ct)
    worst = res > threshold_mm
    rule = f"> {threshold_mm} mm"
    if worst.sum() < 20:
        worst, rule = res >= np.quantile(res, 0.99), "worst 1 %"
    S_inv = np.linalg.inv(S)
    closest, _ = ref.closest(V_ct)
    true_pts = closest @ S_inv[:3, :3].T + S_inv[:3, 3]  # each vertex's closest CT point, in the mesh's frame
    K, (H, W) = seq.intrinsics, HW
    out = dict(fold=fold, rule=rule, n_worst=int(worst.sum()), n_vertices=len(V), max_mm=float(res.max()))
    for k in (2, 8, 30):
        par, per_mm = {True: [], False: []}, {True: [], False: []}
        for i in range(len(poses) - k):
            a, za = project(V, poses[i], K)
            b, _ = project(true_pts, poses[i], K)
            c, zc = project(V, poses[i + k], K)
            d, _ = project(true_pts, poses[i + k], K)
            ok = (za > 0) & (zc > 0)
            for uv in (a, c):
                ok &= (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
            p = np.linalg.norm((c - d) - (a - b), axis=1)
            for w in (True, False):
                par[w].append(p[ok & (worst == w)])
                # per mm of error (vertices off by more than 0.2 mm): how visible an error there is at all
                per_mm[w].append((p / np.maximum(res, 1e-9))[ok & (worst == w) & (res > 0.2)])
        for w, tag in ((True, "worst"), (False, "rest")):
            v = np.concatenate(par[w])
            out[f"parallax_px_k{k}_{tag}"] = [float(np.median(v)), float(np.percentile(v, 90))] if len(v) else None
            v = np.concatenate(per_mm[w])
            out[f"parallax_px_per_mm_k{k}_{tag}"] = float(np.median(v)) if len(v) else None
    # photo-consistency at k = 8 through the mesh's rendered depth
    rend = MeshRenderer(str(seq_dir / "mesh.ply"))
    grey = torch.from_numpy(np.stack([seq.load_frame(i).astype(np.float32).mean(-1) / 255 for i in range(len(seq))]))
    renders = [rend.render(K, poses[i], H, W) for i in range(len(seq))]
    depth = torch.from_numpy(np.stack([r["depth"] for r in renders]))
    mask = torch.from_numpy(seq.mask)
    sums, counts = np.zeros(len(V)), np.zeros(len(V))
    f_xy, c_xy = torch.tensor([K[0, 0], K[1, 1]]), torch.tensor([K[0, 2], K[1, 2]])
    for i in range(len(seq)):
        P = torch.from_numpy(renders[i]["points_world"]).double()
        tri = renders[i]["triangle_ids"]
        for j in (i - 8, i + 8):
            if not 0 <= j < len(seq):
                continue
            Tj = torch.from_numpy(poses[j])
            Xc = P @ Tj[:3, :3].T + Tj[:3, 3]
            z = Xc[..., 2]
            uv = Xc[..., :2] / z.clamp_min(1e-9)[..., None] * f_xy + c_xy
            grid = torch.stack([(uv[..., 0] + 0.5) / W * 2 - 1, (uv[..., 1] + 0.5) / H * 2 - 1], -1).float()[None]
            warped = F.grid_sample(grey[j][None, None], grid, align_corners=False)[0, 0]
            d_j = F.grid_sample(depth[j][None, None], grid, mode="nearest", align_corners=False)[0, 0]
            m_j = F.grid_sample(mask[None, None].float(), grid, mode="nearest", align_corners=False)[0, 0] > 0.5
            seen = torch.from_numpy(tri >= 0) & mask & m_j & (z > 0) & ((d_j - z.float()).abs() < 0.02 * z.float())
            c, good = ncc(grey[i], warped, seen & (grid[0].abs() < 1).all(-1))
            sel = good.numpy()
            for corner in range(3):
                np.add.at(sums, T[tri[sel], corner], c.numpy()[sel])
                np.add.at(counts, T[tri[sel], corner], 1)
    score = sums / np.maximum(counts, 1)
    seen = counts > 5
    out["ncc_k8_worst"] = float(np.median(score[seen & worst])) if (seen & worst).any() else None
    out["ncc_k8_rest"] = float(np.median(score[seen & ~worst]))
    return out


def main(argv: list[str]) -> None:
    args = dict(a.split("=", 1) for a in argv)
    run_root = Path(args.get("run_root", ROOT / "outputs"))
    folds = [int(f) for f in args.get("folds", "0,1,2,3").split(",")]
    for fold in folds:
        r = analyse(run_root, fold, float(args.get("threshold_mm", 1.5)))
        print(f"patient {fold}: max {r['max_mm']:.3f} mm; worst patch ({r['rule']}): {r['n_worst']} of "
              f"{r['n_vertices']} vertices")
        for k in (2, 8, 30):
            w, o = r[f"parallax_px_k{k}_worst"], r[f"parallax_px_k{k}_rest"]
            print(f"  parallax of the error, frames {k:2d} apart (median / p90 px): worst {w[0]:.2f} / {w[1]:.2f}, "
                  f"rest {o[0]:.2f} / {o[1]:.2f}; per mm of error (median): worst "
                  f"{r[f'parallax_px_per_mm_k{k}_worst']:.2f}, rest {r[f'parallax_px_per_mm_k{k}_rest']:.2f}")
        print(f"  photo-consistency (NCC, frames 8 apart, median per vertex): worst {r['ncc_k8_worst']:.3f}, "
              f"rest {r['ncc_k8_rest']:.3f}")


if __name__ == "__main__":
    main(sys.argv[1:])

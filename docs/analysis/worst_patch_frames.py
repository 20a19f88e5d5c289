"""Which frames put a reconstruction's worst patch where it is?

    python docs/analysis/worst_patch_frames.py [run_root=outputs] [fold=1] [threshold_mm=2.0] [local_scaling=true]

For the held-out patient of fold ``fold`` of a ``benchmarks/paper_table.py`` run: the vertices of the last
iteration's mesh farther than ``threshold_mm`` from the CT (registered with the Sim(3) the iteration's evaluation
found) are the worst patch.  For every frame that sees them (unoccluded, inside the mask), prints the median of

* the patch's ground-truth depth (mm, and in multiples of the frame's median depth),
* the network's depth there over the ground truth (the network's depth, in SfM units, scaled by the Sim(3)'s
  scale; 1 = right, < 1 = too near), as inference makes it (Depth Scaling Layer, local scaling with
  ``local_scaling=true``, flip averaging),
* the mesh's depth there over the ground truth,
* the network's std there over the frame's median std.

Ground truth is read here only to judge; this is an analysis, not part of any run.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main(argv: list[str]) -> None:
    from hydra import compose, initialize_config_dir

    import endorecon.utils.resolvers  # noqa: F401
    from endorecon.data.dataset import load_ground_truth
    from endorecon.data.sequence import read_poses_txt
    from endorecon.evaluation.meshes import ReferenceSurface, load_mesh
    from endorecon.rendering.raycast import MeshRenderer, load_mesh_arrays
    from endorecon.tasks import pipeline
    from endorecon.tasks.reconstruct import load_module
    from endorecon.tasks.train import prepare_sequences
    from worst_patch_parallax import project  # this folder's other analysis (run as a script, it is on the path)

    args = dict(a.split("=", 1) for a in argv)
    run_root = Path(args.get("run_root", ROOT / "outputs")).resolve()
    fold, threshold = int(args.get("fold", 1)), float(args.get("threshold_mm", 2.0))
    fold_dir = run_root / "train" / f"fold={fold}"
    it = max(int(p.name.split("=")[1]) for p in fold_dir.glob("iteration=*"))
    # the run's data and SfM cache: its own, else the default output root's (a run made with paths.output_root=...)
    shared = run_root if (run_root / "cache" / "sfm").is_dir() else ROOT / "outputs"
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"fold={fold}", f"paths.output_root={run_root}",
                                                      f"paths.data_dir={shared / 'data'}",
                                                      f"paths.cache_dir={shared / 'cache'}",
                                                      f"paths.run_dir='{fold_dir}'"])
    info = pipeline.load_sequences(cfg)
    sfm_seq = next(s for s in pipeline.run_sfm(cfg, info.sequences, info.root) if s.patient == fold)
    prep = prepare_sequences(cfg, [sfm_seq], fold_dir / f"iteration={it - 1}" if it > 0 else None)[0]
    seq = prep.seq
    module, _ = load_module(fold_dir / f"iteration={it}" / "checkpoints" / "last.ckpt")
    if args.get("local_scaling", "true").lower() == "false":
        module.local_scaling = None
    depth, std, _ = pipeline.infer_depth(module, seq, prep.cache)
    depth, std = depth[:, 0].numpy(), std[:, 0].numpy()
    sdir = fold_dir / f"iteration={it}" / "sequences" / pipeline._slug(seq.name)
    _, poses = read_poses_txt(sdir / "poses.txt")
    V, _ = load_mesh_arrays(str(sdir / "mesh.ply"))
    sim3 = json.loads((fold_dir / f"iteration={it}" / "evaluation" / "metrics.json").read_text())["sim3"]
    S, scale = np.array(sim3["matrix"]), float(sim3["scale"])
    gt = load_ground_truth(info.root, fold, seq.name.split("/")[-1])
    res = ReferenceSurface(load_mesh(gt.mesh_path)).distance(V @ S[:3, :3].T + S[:3, 3])
    patch = V[res > threshold]
    print(f"fold {fold}, iteration {it}: {len(patch)} of {len(V)} vertices over {threshold} mm (max {res.max():.3f} mm)")
    renderer = MeshRenderer(str(sdir / "mesh.ply"))
    K, (H, W) = seq.intrinsics, (seq.height, seq.width)
    gh, gw = gt.depth_mm.shape[1:]
    for i in range(len(seq)):
        rendered = renderer.render(K, poses[i], H, W)["depth"]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv, z = project(patch, poses[i], K)
            u, v = np.round(uv).T.astype(int)
        ok = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        ok[ok] &= seq.mask[v[ok], u[ok]] & (np.abs(rendered[v[ok], u[ok]] - z[ok]) < 0.03 * z[ok])
        if ok.sum() < 10:
            continue
        u, v, z = u[ok], v[ok], z[ok]
        # the GT pixel under this pixel's centre (GT depth is at the dataset's resolution)
        gu = np.clip(np.round((u + 0.5) * gw / W - 0.5).astype(int), 0, gw - 1)
        gv = np.clip(np.round((v + 0.5) * gh / H - 0.5).astype(int), 0, gh - 1)
        d_gt = gt.depth_mm[i][gv, gu]
        g = d_gt > 0
        if g.sum() < 10:
            continue
        median_gt = np.median(gt.depth_mm[i][gt.depth_mm[i] > 0])
        print(f"frame {i:3d}: {int(g.sum()):5d} seen, GT depth {np.median(d_gt[g]):6.1f} mm "
              f"({np.median(d_gt[g]) / median_gt:.1f}x the frame's median), network / GT "
              f"{np.median(depth[i][v, u][g] * scale / d_gt[g]):.3f}, mesh / GT {np.median(z[g] * scale / d_gt[g]):.3f}, "
              f"std / the frame's median std {np.median(std[i][v, u][g]) / np.median(std[i][seq.mask]):.2f}")


if __name__ == "__main__":
    main(sys.argv[1:])

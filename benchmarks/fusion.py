"""Benchmark: adaptive TSDF (endorecon.fusion) vs Open3D's own VoxelBlockGrid.integrate.

The same noisy frames of an analytic tube (radius 7.5 mm, camera moving inside
it, 256x320, ~100 frames) go through both, at the same voxel size and
truncation band, in one run. Reports warm frames/s (best of N, interleaved;
compile time of the adaptive kernel reported separately), their ratio, and the
accuracy of each mesh against the analytic surface (distance of mesh vertices
to the tube, mm).

    .venv/bin/python benchmarks/fusion.py                 # 1 mm and 0.5 mm, 100 frames
    .venv/bin/python benchmarks/fusion.py --frames 30 --voxels 1.0 --repeats 2   # quick

Open3D is called with the half-pixel-corrected K (see PlainTSDF).

OpenMP: torch and Open3D each keep an OpenMP pool; with the default (active)
wait policy the idle pool spins and the other library's threads starve
(measured on the shared 2-core machine: ~10x slower, erratic). This script
therefore sets ``OMP_WAIT_POLICY=PASSIVE`` unless it is set already; it must
be set before torch / Open3D are imported.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import sys  # noqa: E402
import time
from pathlib import Path

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from endorecon.fusion import AdaptiveTSDF, PlainTSDF  # noqa: E402

H, W = 256, 320
K = np.array([[200.0, 0.0, 159.5], [0.0, 200.0, 127.5], [0.0, 0.0, 1.0]])  # pixel-centre convention
RADIUS = 7.5  # mm


def look_along(center: np.ndarray, direction: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    z = direction / np.linalg.norm(direction)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ center
    return T


def tube_frame(T: np.ndarray, rng: np.random.Generator, depth_max: float):
    """Noisy z-depth, per-pixel std and colour of the tube x^2 + y^2 = RADIUS^2 seen by ``T``."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, t = T[:3, :3], T[:3, 3]
    C = -R.T @ t
    D = d_cam @ R  # world ray directions, camera z component 1 -> t is z-depth
    a = D[..., 0] ** 2 + D[..., 1] ** 2
    b = 2 * (C[0] * D[..., 0] + C[1] * D[..., 1])
    c = C[0] ** 2 + C[1] ** 2 - RADIUS**2
    z = (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0))) / (2 * np.maximum(a, 1e-12))
    P = C + z[..., None] * D
    # std grows with depth and towards the image border, like a network's
    r_img = np.hypot((u - K[0, 2]) / W, (v - K[1, 2]) / H)
    std = 0.03 + 0.004 * z + 0.1 * r_img
    depth = z + std * rng.standard_normal(z.shape)
    depth[(z > depth_max) | (a < 1e-9)] = 0.0
    ang = np.arctan2(P[..., 1], P[..., 0])
    color = np.stack([0.6 + 0.3 * np.sin(3 * ang), 0.4 + 0.2 * np.cos(P[..., 2] / 2), 0.3 + 0.0 * z], -1)
    return depth.astype(np.float32), std.astype(np.float32), color.clip(0, 1).astype(np.float32)


def make_frames(n: int, depth_max: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        s = i / max(n - 1, 1)
        c = np.array([2.0 * np.cos(4 * np.pi * s), 2.0 * np.sin(4 * np.pi * s), 30.0 * s])
        look = np.array([0.35 * np.cos(2 * np.pi * s + 1), 0.35 * np.sin(2 * np.pi * s + 1), 1.0])
        T = look_along(c, look)
        d, sd, col = tube_frame(T, rng, depth_max)
        frames.append(dict(depth=torch.from_numpy(d), std=torch.from_numpy(sd), color=torch.from_numpy(col), K=K, cam_from_world=T))
    return frames


def fuse(vol, frames) -> float:
    t0 = time.perf_counter()
    for f in frames:
        vol.integrate(f["depth"], f["std"], f["color"], f["K"], f["cam_from_world"])
    if vol.tdevice.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def tube_error(vol) -> tuple[float, float, int]:
    p = vol.extract_mesh().vertex.positions.cpu().numpy().astype(np.float64)
    d = np.abs(np.hypot(p[:, 0], p[:, 1]) - RADIUS)
    return float(d.mean()), float(np.median(d)), len(p)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--voxels", type=float, nargs="+", default=[1.0, 0.5], help="voxel sizes in mm")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--trunc-voxels", type=float, default=6.0, help="plain truncation = adaptive floor, in voxels")
    ap.add_argument("--depth-max", type=float, default=40.0, help="mm")
    ap.add_argument("--device", default="CPU:0")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--std-mode", default="propagate", choices=["propagate", "average"])
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    t0 = time.perf_counter()
    frames = make_frames(args.frames, args.depth_max)
    print(f"{len(frames)} frames {H}x{W} of a {2 * RADIUS:.0f} mm tube rendered in {time.perf_counter() - t0:.1f} s; "
          f"torch threads {torch.get_num_threads()}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, device {args.device}")
    rows = []
    for voxel in args.voxels:
        blocks = int(4 * (2 * np.pi * RADIUS * 60) * (args.trunc_voxels * 2 + 8) / (8 * voxel) ** 3 * 8) + 20000

        def adaptive():
            return AdaptiveTSDF(voxel, trunc_std_multiplier=3.0, trunc_min_voxels=args.trunc_voxels, depth_max=args.depth_max,
                                block_count=blocks, std_mode=args.std_mode, compile=not args.no_compile, device=args.device)

        def plain():
            return PlainTSDF(voxel, trunc_voxels=args.trunc_voxels, depth_max=args.depth_max, block_count=blocks, device=args.device)

        # warm-up: compile + first touches, on a few frames
        warm = adaptive()
        t_first = fuse(warm, frames[:3])
        compile_s = warm.compile_seconds
        fuse(plain(), frames[:3])
        times = {"adaptive": [], "open3d": []}
        vols = {}
        for _ in range(args.repeats):  # interleaved: A, O, A, O, ...
            for name, mk in (("adaptive", adaptive), ("open3d", plain)):
                vol = mk()
                times[name].append(fuse(vol, frames))
                vols[name] = vol
        fps = {k: len(frames) / min(v) for k, v in times.items()}
        err = {k: tube_error(v) for k, v in vols.items()}
        ratio = fps["adaptive"] / fps["open3d"]
        print(f"\nvoxel {voxel} mm: blocks used {vols['adaptive'].vbg.hashmap().size()} (adaptive) / {vols['open3d'].vbg.hashmap().size()} (open3d)")
        if compile_s is not None:
            print(f"  adaptive first call (torch.compile): {compile_s:.1f} s   (first 3 frames {t_first:.1f} s)")
        for k in ("adaptive", "open3d"):
            ts = ", ".join(f"{t:.2f}" for t in times[k])
            print(f"  {k:9s} {fps[k]:7.1f} frames/s  (runs: {ts} s)   error vs tube: mean {err[k][0]:.4f} mm, "
                  f"median {err[k][1]:.4f} mm, {err[k][2]} vertices")
        print(f"  ratio adaptive / open3d: {ratio:.2f}")
        rows.append((voxel, fps["adaptive"], fps["open3d"], ratio, err["adaptive"][0], err["open3d"][0], err["adaptive"][1], err["open3d"][1]))
    print("\nvoxel_mm  adaptive_fps  open3d_fps  ratio  mean_err_adaptive_mm  mean_err_open3d_mm  median_err_adaptive_mm  median_err_open3d_mm")
    for r in rows:
        print(f"{r[0]:8.2f}  {r[1]:12.1f}  {r[2]:10.1f}  {r[3]:5.2f}  {r[4]:20.4f}  {r[5]:18.4f}  {r[6]:22.4f}  {r[7]:20.4f}")
    return rows


if __name__ == "__main__":
    main()

"""Benchmark: dense pose graph optimisation, its constants computed once vs again at every evaluation.

With ``pgo.freeze_std`` the NLLs' stds are carried between frames at the fixed SfM poses, so they are
constants of the optimisation: ``optimize_poses`` computes them once per edge (``std_cache_mb`` > 0, the
default) instead of once per objective evaluation (``std_cache_mb=0``: the consistency term's carried std is
recomputed per evaluation; the flow std is cached either way).  The peer ``freeze_std=false`` carries them at
the current poses (the cost before freezing).  ``flow_at_points=false`` evaluates the sparse flow term as
dense flow maps at every pixel (the cost before the points were back-projected once per edge).  Scene: the tests' analytic cavity (tests/pgo/synthetic_scene.py)
at the CPU default's PGO size (64x80, half the 128x160 network resolution), 30 frames, neighbours 5-8 both
ways, depth with a smooth 3 % error, poses off by ~0.1° / 0.3 % of the depth (about SfM's on the phantom),
flow with 0.2 px noise, the settings of conf/pgo/default.yaml (10 L-BFGS iterations).

    .venv/bin/python benchmarks/pgo.py [--frames 30] [--repeats 3] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "pgo"))

from endorecon.geometry import rotation_angle_deg, se3_exp  # noqa: E402
from endorecon.pgo import optimize_poses  # noqa: E402
from synthetic_scene import make_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1: no OpenMP spin-waiting on 2 cores)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    scene = make_scene(n_frames=args.frames)
    g = torch.Generator().manual_seed(3)
    n = args.frames
    # a smooth multiplicative depth error (network-like bias) and ~0.1° / 0.3 % pose noise on frames 1..
    bump = torch.nn.functional.interpolate(torch.randn(n, 1, 4, 5, generator=g, dtype=torch.float64), size=(64, 80),
                                           mode="bilinear", align_corners=False)
    depth = (scene.depth * (1 + 0.03 * bump)).float()
    std = 0.05 * depth
    xi = torch.cat([0.003 * torch.randn(n, 3, generator=g, dtype=torch.float64) / 3**0.5,
                    np.deg2rad(0.1) * torch.randn(n, 3, generator=g, dtype=torch.float64) / 3**0.5], 1)
    xi[0] = 0
    T_init = se3_exp(xi) @ scene.cam_from_world
    flow_fn = lambda i, j: scene.sparse_flow_fn(i, j, noise_px=0.2)  # noqa: E731

    # the pipeline's settings (conf/pgo/default.yaml: 10 L-BFGS iterations), not optimize_poses' own defaults
    from omegaconf import OmegaConf

    conf = {k: v for k, v in OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "pgo" / "default.yaml")).items()
            if k not in ("enabled", "resolution_scale")}
    conf["progress"] = False
    variants = {
        "frozen, cached (default)": {},
        "frozen, carried per evaluation": {"std_cache_mb": 0},
        "flow maps at every pixel": {"flow_at_points": False},
        "free stds (freeze_std=false)": {"freeze_std": False},
    }
    times, results = {}, {}
    for _ in range(args.repeats):  # interleaved, so that a busy core hits every variant alike
        for name, over in variants.items():
            t = time.perf_counter()
            results[name] = optimize_poses(depth, std, scene.K.float(), T_init, scene.mask, flow_fn,
                                           {**conf, **over})
            times.setdefault(name, []).append(time.perf_counter() - t)

    base = statistics.median(times["frozen, cached (default)"])
    print(f"PGO, {n} frames 64x80, {len(results['frozen, cached (default)'].edges)} edges, "
          f"{len(results['frozen, cached (default)'].history)} L-BFGS iterations (conf/pgo/default.yaml), "
          f"{args.threads} thread(s), median of {args.repeats}:")
    ref = results["frozen, cached (default)"].cam_from_world
    for name, ts in times.items():
        med = statistics.median(ts)
        res = results[name]
        d_rot = float(rotation_angle_deg(res.cam_from_world[:, :3, :3] @ ref[:, :3, :3].transpose(1, 2)).max())
        print(f"  {name:32s} {med:6.2f} s  (x{med / base:.2f} of cached)  loss {res.loss_before:.5g} -> "
              f"{res.loss_after:.5g}, max rotation from cached {d_rot:.2e}°")


if __name__ == "__main__":
    main()

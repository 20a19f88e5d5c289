"""Benchmark: the SfM stage on a generated phantom (GT poses + mesh) and on the real sinus_example clip.

Phantom: registered fraction, camera-centre RMSE after Sim(3) (Umeyama on the centres) relative to
the GT trajectory length, mean relative-rotation error of consecutive frames, median distance of the
sparse points (after the same Sim(3)) to the GT mesh in mm.
sinus_example (1920x1080 -> 960x540): registered frames and the same trajectory numbers against the
shipped motion.yaml (SfM units).  Time per frame = the stage's wall time / frames (all attempts).  The
peer: the phantom's SfM again with one thread and a seed (``sfm.num_threads=1 sfm.seed=0``, which makes runs
repeat bit for bit), and
the ratio of the two wall times.

    .venv/bin/python benchmarks/sfm.py                     # phantom 40 frames 256x320 + sinus_example
    .venv/bin/python benchmarks/sfm.py --skip-sinus --frames 20
Outputs go to --work (default /tmp/endorecon_bench_sfm), reused when complete: pass --fresh to redo.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from omegaconf import OmegaConf  # noqa: E402

from endorecon.sfm import stage  # noqa: E402
from endorecon.sfm.metrics import aligned_points, point_to_mesh_distance, trajectory_error  # noqa: E402


def _report(name: str, out: Path, res, ref_cam_from_world, mesh=None) -> dict:
    log = json.loads((out / "attempts.json").read_text())
    err = trajectory_error(res.cam_from_world, ref_cam_from_world)
    row = dict(
        sequence=name,
        registered=f"{int(res.registered.sum())}/{len(res)}",
        attempts=len(log["attempts"]),
        points=len(res.points_xyz),
        center_rmse_rel_pct=round(100 * err["center_rmse_rel"], 3),
        rel_rotation_deg=round(err["rel_rotation_deg"], 4),
        rel_translation_rel_pct=round(100 * err["rel_translation_rel"], 2),
        seconds=log["seconds"],
        seconds_per_frame=log["seconds_per_frame"],
        scale_factor=log["scale_factor"],
    )
    if mesh is not None:
        d = point_to_mesh_distance(aligned_points(res.points_xyz, err["sim3"]), mesh)
        row.update(points_to_mesh_median_mm=round(float(np.median(d)), 4),
                   points_to_mesh_p90_mm=round(float(np.percentile(d, 90)), 4))
    print(json.dumps(row))
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--work", type=Path, default=Path("/tmp/endorecon_bench_sfm"))
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--skip-sinus", action="store_true")
    ap.add_argument("--skip-phantom", action="store_true")
    ap.add_argument("--skip-peer", action="store_true", help="no single-thread run of the phantom (the peer)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.fresh and args.work.exists():
        shutil.rmtree(args.work)
    cfg = OmegaConf.load(ROOT / "conf" / "sfm" / "default.yaml")

    if not args.skip_phantom:
        from endorecon.data.dataset import load_dataset, load_ground_truth
        from endorecon.phantom.generate import generate

        ph = args.work / f"phantom_{args.frames}"
        if not (ph / "COMPLETE").is_file():
            generate(ph, patients=1, frames=args.frames)
        seq = load_dataset(ph)[0]
        gt = load_ground_truth(ph, 0)
        out = stage.run(cfg, seq, args.work / f"sfm_phantom_{args.frames}")
        row = _report("phantom", out, stage.load_result(out), gt.cam_from_world, gt.mesh_path)
        if not args.skip_peer:
            # the peer: the same stage with one thread and a seed (the reproducible setting)
            one = OmegaConf.merge(cfg, {"num_threads": 1, "seed": 0})
            out1 = stage.run(one, seq, args.work / f"sfm_phantom_{args.frames}_1thread")
            row1 = _report("phantom, sfm.num_threads=1 sfm.seed=0", out1, stage.load_result(out1), gt.cam_from_world,
                           gt.mesh_path)
            print(f"all threads vs one: {row['seconds']:.1f} vs {row1['seconds']:.1f} s "
                  f"(x{row1['seconds'] / row['seconds']:.2f} faster with all threads)")

    if not args.skip_sinus:
        from endorecon.data.original import load_original

        sinus = ROOT.parent / "shared" / "data" / "sinus_example"
        ref = load_original(sinus)
        out = stage.run(cfg, ref, args.work / "sfm_sinus")  # max_size 960 -> 960x540
        _report("sinus_example", out, stage.load_result(out), ref.cam_from_world)


if __name__ == "__main__":
    main()

"""How failure detection's scores sit around a failure, and what its hysteresis does to a stage's mesh.

    python docs/analysis/hysteresis_screen.py scores [runs=outputs/s43,outputs/s44]
    python docs/analysis/hysteresis_screen.py stage run_root=outputs/s43 fold=2 iteration=2 patient=9 \\
        [lows=off,1.0,0.5] [data_dir=outputs/data] [cache_dir=outputs/cache] [out=outputs/hysteresis_screen]

``scores``: every ``failures.csv`` of every sequence, iteration and fold of the training runs under ``runs``;
the dense simulation loss of the unflagged checks with no flagged neighbour, of those next to a flagged one,
and of the flagged ones; for the train-only patients (4 and up, no CT) and for all.

``stage``: one sequence's end-of-iteration stage made again from the trained previous stage, with that
iteration's network, once per low threshold (``off``: no hysteresis), and each mesh registered to the
patient's ground-truth surface.  Train-only patients' surfaces are read here, as the README's screens do;
no run reads them.
"""

from __future__ import annotations

import csv
import re
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def _args(argv: list[str]) -> dict[str, str]:
    return dict(a.split("=", 1) for a in argv if "=" in a)


def scores(runs: list[Path]) -> None:
    groups = {True: {"away": [], "next": [], "flagged": []}, False: {"away": [], "next": [], "flagged": []}}
    for run in runs:
        for f in sorted(run.glob("train/fold=*/iteration=*/sequences/*/failures.csv")):
            patient = int(re.search(r"patient_(\d+)__", str(f)).group(1))
            rows = list(csv.DictReader(f.read_text().splitlines()))
            for k, r in enumerate(rows):
                ds = float(r["dense_simulation"])
                if int(r["flagged"]):
                    kind = "flagged"
                else:
                    near = any(int(rows[j]["flagged"]) for j in (k - 1, k + 1) if 0 <= j < len(rows))
                    kind = "next" if near else "away"
                for train_only in (True, False):
                    if patient >= 4 or not train_only:
                        groups[train_only][kind].append(ds)
    for train_only, g in groups.items():
        print("train-only patients (4 and up)" if train_only else "all patients")
        away, near, flagged = (np.array(g[k]) for k in ("away", "next", "flagged"))
        if len(away):
            print(f"  unflagged, no flagged neighbour: {len(away)}, highest {np.nanmax(away):.2f}")
        print(f"  unflagged, next to a flagged one: {len(near)}: "
              + ", ".join(f"{v:.2f}" for v in np.sort(near)[::-1]))
        if len(flagged):
            print(f"  flagged: {len(flagged)}, lowest {np.nanmin(flagged):.2f}")


def stage(a: dict[str, str]) -> None:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import endorecon.utils.resolvers  # noqa: F401
    from endorecon.data.sequence import read_poses_txt
    from endorecon.tasks import pipeline
    from endorecon.tasks.reconstruct import load_module
    from endorecon.tasks.train import prepare_sequences

    run = Path(a["run_root"]).resolve()
    fold, it, patient = int(a["fold"]), int(a["iteration"]), int(a["patient"])
    fold_dir = run / "train" / f"fold={fold}"
    out_root = Path(a.get("out", "outputs/hysteresis_screen")).resolve() / f"{run.name}_f{fold}_it{it}_p{patient}"
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[
            f"fold={fold}", f"paths.output_root={run}", f"paths.run_dir='{fold_dir}'",
            f"paths.data_dir={Path(a.get('data_dir', 'outputs/data')).resolve()}",
            f"paths.cache_dir={Path(a.get('cache_dir', 'outputs/cache')).resolve()}"])
    # the stage's inputs do not depend on the low threshold: loaded and inferred once
    info = pipeline.load_sequences(cfg)
    seq = [s for s in pipeline.run_sfm(cfg, info.sequences, info.root) if s.patient == patient][0]
    prep = prepare_sequences(cfg, [seq], fold_dir / f"iteration={it - 1}" if it > 0 else None)[0]
    module, _ = load_module(fold_dir / f"iteration={it}" / "checkpoints" / "last.ckpt")
    depth, std, colors = pipeline.infer_depth(module, prep.seq, prep.cache)
    surface = info.root / "ground_truth" / f"patient_{patient:02d}" / "mesh.ply"
    for low in a.get("lows", "off,1.0").split(","):
        cfg.failure.low_thresholds = None if low == "off" else OmegaConf.create({"dense_simulation": float(low)})
        od = out_root / low
        summary = pipeline.refine_sequence(cfg, prep.seq, prep.cache, depth, std, colors, prep.excluded, od)
        _, poses = read_poses_txt(od / "poses.txt")
        ev = pipeline.evaluate_against_ct(info.root, prep.seq, od / "mesh.ply", poses, od / "evaluation", surface)
        print(f"{run.name} fold {fold} iteration {it} patient {patient}, low threshold {low}: flagged "
              f"{summary['flagged']} (hysteresis {summary.get('flagged_low')}), mean / max {ev['mean_mm']:.3f} / "
              f"{ev['max_mm']:.3f} mm, {ev['ct_covered_mm2'] / 100:.1f} cm2", flush=True)


if __name__ == "__main__":
    what, a = (sys.argv[1] if len(sys.argv) > 1 else ""), _args(sys.argv[2:])
    if what == "scores":
        scores([Path(r) for r in a.get("runs", "outputs/s43,outputs/s44,outputs/s45,outputs/s45b,outputs/s45c")
                .split(",")])
    elif what == "stage":
        stage(a)
    else:
        sys.exit(__doc__)

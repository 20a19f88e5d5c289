"""The paper's question on the phantom: how much does each part buy, in mm?

    python benchmarks/paper_table.py [folds=0,1,2,3] [any train.py override ...]

For each leave-one-out fold: trains it (``train.py``, skipped when complete),
then evaluates the held-out patient's mesh and its ablations against the
patient's CT (see :mod:`endorecon.tasks.ablation`).  Writes
``outputs/benchmarks/paper_table/results.{md,csv}`` and prints the table.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def trained_with_other_stage_settings(cfg) -> list[str] | None:
    """What differs, when the fold's run dir holds every iteration up to ``cfg.iteration``, each made with other
    settings of the end-of-iteration stages (fusion / failure / PGO) only: ``train.py`` refuses to reuse such a
    fold, while its ``full`` and ``iteration0`` rows can be made again with the current settings
    (:func:`endorecon.tasks.ablation.refuse_iteration`, ``*`` in the table).  None otherwise: incomplete, or
    another setting differs too."""
    from endorecon.tasks.pipeline import REFINE_SETTINGS
    from endorecon.tasks.train import is_complete, iteration_dir, recorded_differences

    its = range(int(cfg.iteration) + 1)
    if not all(is_complete(iteration_dir(cfg, it)) for it in its):
        return None
    diffs, recorded = [], 0
    for _, _, d in recorded_differences(cfg):
        recorded += 1
        if any(x.split(".")[0] not in REFINE_SETTINGS for x in d):
            return None
        diffs += [x for x in d if x not in diffs]
    return diffs if recorded == len(its) and diffs else None


def main(argv: list[str]) -> None:
    from hydra import compose, initialize_config_dir

    import endorecon.utils.resolvers  # noqa: F401
    from endorecon.tasks import ablation
    from endorecon.tasks.train import run as train_run

    folds, overrides = [0, 1, 2, 3], []
    for a in argv:
        if a.startswith("folds="):
            folds = [int(v) for v in a.split("=", 1)[1].split(",")]
        else:
            overrides.append(a)
    rows, t0 = [], time.perf_counter()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        probe = compose(config_name="train", overrides=overrides)
        table_dir = Path(probe.paths.output_root) / "benchmarks" / "paper_table"
        # a run of some folds keeps the other folds' rows of the table (held-out patient = fold)
        kept = [r for r in ablation.read_table(table_dir / "results.csv") if r["patient"] not in folds]
        if kept:
            print(f"keeping the rows of held-out patient(s) {sorted({r['patient'] for r in kept})} from "
                  f"{table_dir / 'results.csv'}", flush=True)
        for fold in folds:
            fold_dir = Path(probe.paths.output_root) / "train" / f"fold={fold}"
            cfg = compose(config_name="train", overrides=[*overrides, f"fold={fold}", f"paths.run_dir='{fold_dir}'"])
            t = time.perf_counter()
            diffs = trained_with_other_stage_settings(cfg)
            if diffs:  # train.py would refuse it; the table re-makes its last stages instead
                print(f"fold {fold}: trained with other stage settings ({'; '.join(diffs)}); not trained again, "
                      f"its full and iteration0 rows are made again with the current ones (*)", flush=True)
            else:
                train_run(cfg)
                print(f"fold {fold}: trained in {time.perf_counter() - t:.0f} s", flush=True)
            out = Path(cfg.paths.output_root) / "benchmarks" / "paper_table" / f"fold={fold}"
            rows += ablation.run_fold(cfg, fold_dir, out)
            table = sorted(kept + rows, key=lambda r: r["patient"])  # stable: each patient's variants in order
            csv_path, md_path = ablation.write_table(table, out.parent)
    print(md_path.read_text())
    print(f"written {md_path} and {csv_path} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])

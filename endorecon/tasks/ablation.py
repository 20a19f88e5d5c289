"""How much each part of the method buys, in mm: ablations of a trained fold and the results table.

For the held-out patient of a fold (after ``train.py`` made its iterations):

* ``full``            — the last iteration's mesh (adaptive fusion + failure detection + PGO);
* ``plain_fusion``    — the same depths, poses and flags through Open3D's plain TSDF (``fusion=plain``);
* ``no_failure_pgo``  — the same depths, adaptive fusion, SfM poses, no frame excluded;
* ``iteration0``      — no Dense Simulation Loss: the mesh of bootstrapping iteration 0;
* ``gt_upper_bound``  — ground-truth depth fused at ground-truth poses (what fusion alone can reach).

Every variant is registered to the patient's CT with the same Sim(3) + ICP and
reported with the same residual statistics.
"""

from __future__ import annotations

import copy
import csv
import json
import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from endorecon.tasks import pipeline
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_write_text

log = logging.getLogger(__name__)

VARIANTS = ("full", "plain_fusion", "no_failure_pgo", "iteration0", "gt_upper_bound")
COLUMNS = ("mean_mm", "median_mm", "p95_mm", "max_mm", "frac_below_1mm")


def _last_iteration(fold_dir: Path) -> int:
    its = sorted(int(p.parent.name.split("=")[1]) for p in fold_dir.glob("iteration=*/metrics.json"))
    if not its:
        raise InputError("no complete bootstrapping iteration", fold_dir, "run python train.py fold=<k> first")
    return its[-1]


def _variant_cfg(cfg: DictConfig, **changes) -> DictConfig:
    c = copy.deepcopy(cfg)
    OmegaConf.set_struct(c, False)
    for key, value in changes.items():
        OmegaConf.update(c, key, value, merge=False)
    return c


def fuse_ground_truth(cfg: DictConfig, data_root: Path, seq, out_path: Path, rel_std: float = 0.01) -> Path:
    """Fuse GT depth at GT poses (std = ``rel_std`` x depth) with the configured fusion; the upper bound."""
    from endorecon.data.dataset import load_ground_truth

    if out_path.is_file():
        return out_path
    gt = load_ground_truth(data_root, seq.patient, seq.name.split("/")[-1])
    n = len(seq)
    depth = torch.from_numpy(gt.depth_mm)[:, None].float()
    std = depth * rel_std
    colors = np.stack([seq.load_frame(i) for i in range(n)]).astype(np.float32) / 255.0
    volume = pipeline.fuse_sequence(cfg.fusion, seq, depth, std, colors, gt.cam_from_world, np.ones(n, bool))
    volume.save_mesh(out_path)
    return out_path


def run_fold(cfg: DictConfig, fold_dir: Path, out_dir: Path) -> list[dict]:
    """All variants for the held-out patient of ``cfg.fold``; returns one row per variant."""
    from endorecon.data.dataset import load_ground_truth
    from endorecon.tasks.reconstruct import load_module
    from endorecon.tasks.train import prepare_sequences

    fold_dir, out_dir = Path(fold_dir), Path(out_dir)
    last = _last_iteration(fold_dir)
    info = pipeline.load_sequences(cfg)
    tests = [s for s in info.sequences if s.patient == int(cfg.fold)]
    sfm_seqs = [s for s in pipeline.run_sfm(cfg, info.sequences, info.root) if s.patient == int(cfg.fold)]
    prev = fold_dir / f"iteration={last - 1}" if last > 0 else None
    prepared = prepare_sequences(cfg, sfm_seqs, prev)
    module, _ = load_module(fold_dir / f"iteration={last}" / "checkpoints" / "last.ckpt")
    rows = []
    for raw, prep in zip(tests, prepared):
        slug = pipeline._slug(prep.seq.name)
        gt = load_ground_truth(info.root, raw.patient, raw.name.split("/")[-1])
        if gt.mesh_path is None:
            continue

        def row(variant, ev):
            return {"patient": raw.patient, "sequence": raw.name, "variant": variant,
                    **{k: (ev or {}).get(k) for k in COLUMNS}}

        for variant, it in (("full", last), ("iteration0", 0)):
            m = json.loads((fold_dir / f"iteration={it}" / "metrics.json").read_text())
            rows.append(row(variant, m.get("evaluation")))
        depth = std = colors = None
        for variant, changes in (("plain_fusion", {"fusion.name": "plain"}),
                                 ("no_failure_pgo", {"failure.enabled": False, "pgo.enabled": False})):
            vdir = out_dir / variant / slug
            if not (vdir / "summary.json").is_file() and depth is None:
                depth, std, colors = pipeline.infer_depth(module, prep.seq, prep.cache)
            pipeline.refine_sequence(_variant_cfg(cfg, **changes), prep.seq, prep.cache, depth, std, colors,
                                     None if variant == "no_failure_pgo" else prep.excluded, vdir)
            from endorecon.data.sequence import read_poses_txt

            _, poses = read_poses_txt(vdir / "poses.txt")
            rows.append(row(variant, pipeline.evaluate_against_ct(info.root, prep.seq, vdir / "mesh.ply", poses,
                                                                  vdir / "evaluation")))
        gdir = out_dir / "gt_upper_bound" / slug
        mesh = fuse_ground_truth(cfg, info.root, raw, gdir / "mesh.ply")
        rows.append(row("gt_upper_bound", pipeline.evaluate_against_ct(info.root, raw, mesh, gt.cam_from_world,
                                                                       gdir / "evaluation")))
    return rows


def write_table(rows: list[dict], out_dir: Path) -> tuple[Path, Path]:
    """``results.csv`` and ``results.md``: one row per (patient, variant), then the mean over patients."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fields = ["patient", "sequence", "variant", *COLUMNS]
    lines = [",".join(fields)]
    for r in rows:
        lines.append(",".join("" if r[f] is None else (f"{r[f]:.4f}" if isinstance(r[f], float) else str(r[f]))
                              for f in fields))
    csv_path = atomic_write_text(out_dir / "results.csv", "\n".join(lines) + "\n")
    md = ["| patient | variant | mean (mm) | median (mm) | p95 (mm) | max (mm) | < 1 mm |",
          "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]

    def fmt(r):
        if r["mean_mm"] is None:
            return "| {} | {} | n/a | n/a | n/a | n/a | n/a |".format(r["patient"], r["variant"])
        return "| {} | {} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {:.0%} |".format(
            r["patient"], r["variant"], r["mean_mm"], r["median_mm"], r["p95_mm"], r["max_mm"], r["frac_below_1mm"])

    md += [fmt(r) for r in rows]
    for v in VARIANTS:
        vals = [r for r in rows if r["variant"] == v and r["mean_mm"] is not None]
        if vals:
            mean = {k: float(np.mean([r[k] for r in vals])) for k in COLUMNS}
            md.append(fmt({"patient": "**mean**", "variant": v, **mean}))
    md_path = atomic_write_text(out_dir / "results.md", "\n".join(md) + "\n")
    return csv_path, md_path

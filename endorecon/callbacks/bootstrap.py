"""The end of a bootstrapping iteration, as a Lightning callback.

At ``on_train_end`` every sequence (training patients and the held-out one) is
run through :func:`endorecon.tasks.pipeline.refine_sequence`: depth inference,
adaptive fusion, simulated depth, failure detection, dense PGO, fusion again.
The held-out patient's mesh is copied to the iteration dir and, when its CT
exists, evaluated against it.  ``metrics.json`` is written last: it marks the
iteration complete.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import lightning as L
import numpy as np
import torch

from endorecon.tasks import pipeline
from endorecon.utils.io import atomic_path, atomic_write_text

log = logging.getLogger(__name__)


def _scalar(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _range_name(b: dict) -> str:
    """A TensorBoard tag for a depth band (no '<' / '>')."""
    return f"{b['lo']:g}-{b['hi']:g}x" if b["hi"] is not None else f"over_{b['lo']:g}x"


# bootstrap.targets: key -> (what it checks, how a value passes against the target)
TARGETS = {"abs_rel": ("depth AbsRel", "<="), "std_spearman": ("std-error Spearman", ">"),
           "mean_mm": ("mesh mean residual (mm)", "<"), "max_mm": ("mesh max residual (mm)", "<")}
_OPS = {"<=": lambda v, t: v <= t, "<": lambda v, t: v < t, ">": lambda v, t: v > t}


def log_held_out_report(metrics: dict, targets, it_dir: Path) -> None:
    """Log :func:`held_out_report`'s lines (after an iteration, and for a fold found complete)."""
    for level, line in held_out_report(metrics, targets, it_dir):
        log.log(level, line)


def held_out_report(metrics: dict, targets, it_dir: Path) -> list[tuple[int, str]]:
    """The iteration's held-out results as log lines ``(level, text)``: one INFO summary (depth, mesh, flags),
    the depth error by relative depth, and one WARNING naming each target (``bootstrap.targets``) it misses,
    so that a run that falls short says so where it is watched, not only in ``metrics.json``."""
    from endorecon.evaluation.depth_metrics import format_depth_ranges

    de, ev = metrics.get("depth_evaluation") or {}, metrics.get("evaluation") or {}
    head = f"{metrics.get('iteration')} of fold {metrics.get('fold')}, held-out patient {metrics.get('fold')}:"
    parts = []
    if de:
        parts.append(f"depth AbsRel {de['abs_rel']:.3f}, δ<1.25 {de['a1']:.3f}, std-error Spearman "
                     f"{de.get('std_error_spearman', float('nan')):.2f}")
    if ev:
        parts.append(f"mesh residual mean / median / p95 / max {ev['mean_mm']:.3f} / {ev['median_mm']:.3f} / "
                     f"{ev['p95_mm']:.3f} / {ev['max_mm']:.3f} mm ({100 * ev.get('frac_below_1mm', float('nan')):.0f} % < 1 mm)")
    parts.append(f"{metrics.get('n_flagged', 0)} frame(s) flagged over all sequences")
    lines = [(logging.INFO, f"{head} " + "; ".join(parts))]
    if de.get("by_relative_depth"):
        lines.append((logging.INFO, "held-out depth, mean log error by depth / frame median (+ too far, - too near, "
                                    "share of pixels): " + format_depth_ranges(de["by_relative_depth"])))
    if not de and not ev:
        return lines
    values = {"abs_rel": de.get("abs_rel"), "std_spearman": de.get("std_error_spearman"),
              "mean_mm": ev.get("mean_mm"), "max_mm": ev.get("max_mm")}
    missed = []
    for key, (name, op) in TARGETS.items():
        t, value = (targets or {}).get(key), values[key]
        if t is None or value is None:
            continue
        if not (np.isfinite(value) and _OPS[op](value, float(t))):
            missed.append(f"{name} {value:.3f} (target {op} {float(t):g})")
    if missed:
        where = it_dir / "evaluation" / "residual_heatmap.png" if ev else it_dir / "metrics.json"
        lines.append((logging.WARNING, f"held-out patient {metrics.get('fold')} misses: " + ", ".join(missed)
                      + f"; see {where}"))
    return lines


class BootstrapCallback(L.Callback):
    def __init__(self, cfg, prepared, it_dir: Path, info):
        self.cfg = cfg
        self.prepared = prepared
        self.it_dir = Path(it_dir)
        self.info = info
        self.metrics: dict | None = None

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        t_start = time.perf_counter()
        cfg, it_dir = self.cfg, self.it_dir
        train_metrics = {k: _scalar(v) for k, v in trainer.callback_metrics.items()}
        summaries = []
        rows = ["sequence,frame,dense_simulation,sparse_flow,depth_consistency,flagged,reason"]
        test_seq = None
        depth_eval = depth_eval_capped = None
        # a sequence refined before an interruption is kept only if these weights made it (a run started again
        # without ckpt_path=last trains new ones)
        made_by = pipeline.weights_digest(pl_module)
        for prep in self.prepared:
            seq = prep.seq
            sdir = it_dir / "sequences" / pipeline._slug(seq.name)
            held_out = seq.patient == int(cfg.fold)
            # the held-out sequence is always made again while evaluating: its depth evaluation needs the depth
            summary = None if held_out and cfg.bootstrap.evaluate else pipeline.reusable_summary(sdir, made_by)
            if summary is None:
                depth, std, colors = pipeline.infer_depth(pl_module, seq, prep.cache)
                summary = pipeline.refine_sequence(cfg, seq, prep.cache, depth, std, colors, prep.excluded, sdir,
                                                   made_by=made_by)
                if held_out and cfg.bootstrap.evaluate and depth_eval is None:
                    depth_eval, depth_eval_capped = pipeline.evaluate_depth_with_cap(
                        self.info.root, seq, depth, std, cfg.bootstrap.get("depth_cap_mm"))
            summaries.append(summary)
            csv = (sdir / "failures.csv").read_text().splitlines()
            rows += [f"{seq.name},{line}" for line in csv[1:]]
            if seq.patient == int(cfg.fold) and test_seq is None:
                test_seq = (prep, sdir)
        atomic_write_text(it_dir / "failures.csv", "\n".join(rows) + "\n")

        evaluation = None
        if test_seq is not None:
            prep, sdir = test_seq
            with atomic_path(it_dir / "poses.txt") as tmp:
                shutil.copyfile(sdir / "poses.txt", tmp)
            with atomic_path(it_dir / "mesh.ply") as tmp:
                shutil.copyfile(sdir / "mesh.ply", tmp)
            if cfg.bootstrap.evaluate:
                evaluation = self._evaluate(prep.seq, sdir)
        if depth_eval and depth_eval.get("by_relative_depth"):
            from endorecon.evaluation.plots import save_depth_error_by_range

            save_depth_error_by_range(depth_eval["by_relative_depth"], it_dir / "evaluation" / "depth_error_by_range.png",
                                      f"held-out patient {cfg.fold}, {it_dir.name}: depth error by relative depth")
        self.metrics = dict(
            iteration=self.it_dir.name,
            fold=int(cfg.fold),
            train=train_metrics,
            sequences=summaries,
            n_flagged=int(sum(s["n_flagged"] for s in summaries)),
            evaluation=evaluation,
            depth_evaluation=depth_eval,
            depth_evaluation_capped=depth_eval_capped,
            bootstrap_s=time.perf_counter() - t_start,
        )
        self._log_tensorboard(trainer, summaries, evaluation)
        atomic_write_text(it_dir / "metrics.json", json.dumps(self.metrics, indent=2) + "\n")
        log_held_out_report(self.metrics, cfg.bootstrap.get("targets"), it_dir)

    def _evaluate(self, seq, sdir: Path) -> dict | None:
        """The held-out mesh against the patient's CT (evaluation is the only reader of ground truth)."""
        from endorecon.data.sequence import read_poses_txt

        _, poses = read_poses_txt(sdir / "poses.txt")
        return pipeline.evaluate_against_ct(self.info.root, seq, sdir / "mesh.ply", poses, self.it_dir / "evaluation")

    def _log_tensorboard(self, trainer, summaries, evaluation) -> None:
        exp = getattr(trainer.logger, "experiment", None) if trainer.logger else None
        if exp is None or not hasattr(exp, "add_scalar"):
            return
        step = trainer.global_step
        exp.add_scalar("bootstrap/flagged_frames", sum(s["n_flagged"] for s in summaries), step)
        for s in summaries:
            if s.get("pgo", {}).get("loss_after") is not None:
                exp.add_scalar(f"bootstrap/pgo_loss_after/{s['sequence']}", s["pgo"]["loss_after"], step)
        if evaluation:
            for k in ("mean_mm", "median_mm", "p95_mm", "max_mm"):
                if k in evaluation:
                    exp.add_scalar(f"evaluation/{k}", evaluation[k], step)
        for key, prefix in (("depth_evaluation", "depth_"), ("depth_evaluation_capped", "depth_capped_")):
            for k, v in (self.metrics.get(key) or {}).items():
                if k == "by_relative_depth":
                    for b in v:
                        if b["log_error"] is not None:
                            exp.add_scalar(f"evaluation/{prefix}log_error/{_range_name(b)}", b["log_error"], step)
                elif _scalar(v) is not None:
                    exp.add_scalar(f"evaluation/{prefix}{k}", _scalar(v), step)
        try:
            import open3d as o3d

            mesh = o3d.io.read_triangle_mesh(str(self.it_dir / "mesh.ply"))
            v = torch.from_numpy(np.asarray(mesh.vertices, np.float32))[None]
            f = torch.from_numpy(np.asarray(mesh.triangles, np.int32))[None]
            c = torch.from_numpy((np.asarray(mesh.vertex_colors) * 255).astype(np.uint8))[None]
            if v.shape[1] and c.shape[1] == v.shape[1]:
                exp.add_mesh("bootstrap/mesh", vertices=v, faces=f, colors=c, global_step=step)
        except Exception as e:  # the mesh plugin is a nicety; never fail an iteration over it
            log.warning("could not log the mesh to TensorBoard: %s", e)

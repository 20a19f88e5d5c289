"""How much each part of the method buys, in mm: ablations of a trained fold and the results table.

For the held-out patient of a fold (after ``train.py`` made its iterations):

* ``full``            — the last iteration's mesh (adaptive fusion + failure detection + PGO);
* ``plain_fusion``    — the same depths, poses and flags through Open3D's plain TSDF (``fusion=plain``);
* ``no_failure_pgo``  — the same depths, adaptive fusion, no frame excluded and no PGO in the last stage
  (the poses the previous iteration's PGO left, as ``full`` starts from; SfM's at iteration 0);
* ``iteration0``      — no Dense Simulation Loss: the mesh of bootstrapping iteration 0;
* ``gt_upper_bound``  — ground-truth depth fused at ground-truth poses (what fusion alone can reach);
* ``adapted``         — the application phase of ``reconstruct.py``: the last iteration's network adapted to
  the held-out video by test-time self-supervision (:mod:`endorecon.tasks.adapt`; no label, no CT), then
  failure detection, PGO and adaptive fusion from the SfM poses.  Its network has seen the held-out
  video (not its ground truth), so it is reported beside ``full``, not in its place.

Rows carry the held-out network's depth AbsRel (GT depth, per-frame median scaling) where a variant has
network depth.

Every variant is registered to the patient's CT with the same Sim(3) + ICP and
reported with the same residual statistics, on its mesh as the current fusion config saves it
(:func:`configured_mesh`: meshes of older runs get the configured boundary trim first).  A ``full`` or
``iteration0`` row whose training run used other fusion / failure / PGO settings is made again from
that iteration's network with the current ones, after the earlier iterations' stages that differ as well
(:func:`refuse_iteration`), and marked ``*`` in the table; ``plain_fusion`` and ``no_failure_pgo`` then
start from the previous stage as made again too, so that all three fuse from the same poses and left-out
frames.  The variant dirs record what they were made from (``source.json``) and are rebuilt when it changes.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import logging
import math
import shutil
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from endorecon.data.sequence import read_poses_txt, sfm_fingerprint
from endorecon.tasks import pipeline
from endorecon.tasks.pipeline import REFINE_SETTINGS, refine_settings
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_path, atomic_write_text, file_id, remove_path

log = logging.getLogger(__name__)

VARIANTS = ("full", "plain_fusion", "no_failure_pgo", "iteration0", "gt_upper_bound", "adapted")
# std_residual_spearman: how well the mesh's per-vertex std ranks its residuals (None: the mesh has no std)
COLUMNS = ("mean_mm", "median_mm", "p95_mm", "max_mm", "frac_below_1mm", "ct_covered_mm2", "abs_rel",
           "std_residual_spearman")


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


def _row(seq, variant: str, ev: dict | None, abs_rel: float | None = None) -> dict:
    """One table row: the residual statistics of ``ev`` (None: n/a) and the depth AbsRel."""
    return {"patient": seq.patient, "sequence": seq.name, "variant": variant,
            **{k: (ev or {}).get(k) for k in COLUMNS}, "abs_rel": abs_rel}


def recorded_settings(it_dir: Path) -> dict | None:
    """The settings an iteration of ``train.py`` ran with (its ``.hydra/config.yaml``); None if unknown."""
    try:
        return refine_settings(OmegaConf.load(Path(it_dir) / ".hydra" / "config.yaml"))
    except Exception:
        return None


def settings_diff(old: dict | None, new: dict, ignore: tuple[str, ...] = ("fusion.boundary_trim_rings",)) -> list[str]:
    """``group.key: old -> new`` for every setting that differs (``["settings unrecorded"]`` when ``old`` is
    None), less ``ignore`` (the boundary trim: :func:`configured_mesh` applies it to any saved mesh)."""
    if old is None:
        return ["settings unrecorded"]
    out = []
    for g in REFINE_SETTINGS:
        a, b = old.get(g) or {}, new.get(g) or {}
        out += [f"{g}.{k}: {a.get(k)} -> {b.get(k)}" for k in sorted(set(a) | set(b))
                if a.get(k) != b.get(k) and f"{g}.{k}" not in ignore]
    return out


def _same_source(old, new: dict) -> bool:
    """Whether a recorded ``source.json`` names what ``new`` does: the same checkpoint and SfM model, and
    settings that differ only where nothing differs (a key added to a config since, at the value the old
    run used without it; the boundary trim, which :func:`configured_mesh` applies to any saved mesh)."""
    if not isinstance(old, dict) or set(old) != set(new):
        return False
    if any(old[k] != new[k] for k in old if k != "settings"):
        return False
    a, b = old.get("settings"), new.get("settings")
    if not (isinstance(a, dict) and isinstance(b, dict)) or set(a) != set(b):
        return a == b
    norm_a, norm_b = refine_settings(OmegaConf.create(a)), refine_settings(OmegaConf.create(b))
    return norm_a is not None and norm_b is not None and not settings_diff(norm_a, norm_b)


def _reset_if_other_source(vdir: Path, source: dict, keep: tuple[str, ...] = ()) -> None:
    """Empty ``vdir`` when its outputs came from another source than ``source`` (``{"checkpoint": file id,
    "settings": refine_settings(cfg)}``; a retrained fold, changed fusion settings, or a dir made before
    ``source.json`` was written), then record ``source`` there: the skip-if-done logic of the stages below
    only sees that files exist, not what they were made from.  When only the settings changed, the entries
    named in ``keep`` stay (the adapted network: it depends on the checkpoint, not on the fusion)."""
    vdir = Path(vdir)
    marker = vdir / "source.json"
    try:
        old = json.loads(marker.read_text())
    except (OSError, ValueError):
        old = None
    if old == source or _same_source(old, source):
        return
    if vdir.exists():
        if isinstance(old, dict) and "checkpoint" not in old and "settings" not in old:
            old = {"checkpoint": old}  # a record of the checkpoint alone (before settings were recorded)
        # the SfM model too: another SfM run of the video is another world frame (``sfm``: the digest of its
        # points; a record without it is unrecorded, so made again)
        same_ckpt = (isinstance(old, dict) and old.get("checkpoint") == source.get("checkpoint")
                     and old.get("sfm") == source.get("sfm"))
        log.info("%s was made from another (or an unrecorded) %s: running it again", vdir,
                 "setting" if same_ckpt else "checkpoint or SfM model")
        _empty_dir(vdir, keep if same_ckpt else ())
    vdir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(marker, json.dumps(source, indent=2) + "\n")


def _empty_dir(vdir: Path, keep: tuple[str, ...] = ()) -> None:
    """Delete everything in ``vdir`` except the entries named in ``keep``."""
    for p in Path(vdir).iterdir():
        if p.name not in keep:
            remove_path(p)


def configured_mesh(cfg: DictConfig, mesh_path: Path, out_dir: Path) -> Path:
    """``mesh_path`` as the current fusion config would save it: a mesh saved with fewer boundary rings
    trimmed (``fusion.boundary_trim_rings``; older runs: 0) gets the missing rings trimmed into
    ``out_dir/mesh_trim<k>.ply`` so that every variant of the table is measured the same way."""
    from endorecon.fusion import boundary_trim_rings_of, read_mesh_ply, trim_boundary, write_mesh_ply

    mesh_path = Path(mesh_path)
    want, have = int(cfg.fusion.get("boundary_trim_rings", 0)), boundary_trim_rings_of(mesh_path)
    if have >= want:
        if have > want:
            log.warning("%s was saved with %d boundary rings trimmed, more than the %d configured", mesh_path, have, want)
        return mesh_path
    out = Path(out_dir) / f"mesh_trim{want}.ply"
    record = out.with_suffix(".json")  # which mesh it was trimmed from: a retrained fold's mesh is trimmed again
    made_from = {"mesh": file_id(mesh_path), "rings": want}
    if not out.is_file() or _read_record(record) != made_from:
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:
            write_mesh_ply(tmp, trim_boundary(read_mesh_ply(mesh_path), want - have), boundary_trim_rings=want)
        atomic_write_text(record, json.dumps(made_from, indent=2) + "\n")
    return out


def _read_record(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


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
    ckpt = fold_dir / f"iteration={last}" / "checkpoints" / "last.ckpt"
    module, _ = load_module(ckpt)
    settings = refine_settings(cfg)
    source = {"checkpoint": file_id(ckpt), "settings": settings}  # what the variants below are made from
    rows = []
    for k, (raw, sfm_seq, prep) in enumerate(zip(tests, sfm_seqs, prepared)):
        slug = pipeline._slug(prep.seq.name)
        gt = load_ground_truth(info.root, raw.patient, raw.name.split("/")[-1])
        if gt.mesh_path is None:
            continue

        seq_source = {**source, "sfm": sfm_fingerprint(sfm_seq)}
        abs_rel = {}
        start = prev  # the iteration dir the last stage starts from: as trained, or as made again for `full`
        for variant, it in (("full", last), ("iteration0", 0)):
            it_dir = fold_dir / f"iteration={it}"
            m = json.loads((it_dir / "metrics.json").read_text())
            # the iteration's depth evaluation is of its first held-out sequence only
            abs_rel[variant] = (m.get("depth_evaluation") or {}).get("abs_rel") if k == 0 else None
            diff = settings_diff(recorded_settings(it_dir), settings)
            if diff:  # trained with other fusion / failure / PGO settings: its last stage again, as now set
                ev = refuse_iteration(cfg, info, fold_dir, it, sfm_seq, out_dir / variant, diff)
                rows.append({**_row(raw, variant, ev, abs_rel[variant]), "refused": diff})
                if variant == "full":
                    start = stage_start(fold_dir, it, settings, out_dir / variant)
                continue
            # Evaluated here, not read from the run's metrics.json, so that every row is measured by the
            # current evaluator (the same one gives the same numbers; a changed one recomputes).
            # this sequence's own mesh and poses (the iteration dir's copies are of its first held-out sequence;
            # runs from before the per-sequence dirs have only those)
            sdir = it_dir / "sequences" / slug
            src = sdir if (sdir / "mesh.ply").is_file() and (sdir / "poses.txt").is_file() else it_dir
            if src is it_dir and k > 0:
                raise InputError(f"no mesh of held-out sequence {prep.seq.name} in the training run", sdir,
                                 f"run python train.py fold={int(cfg.fold)} again with the current code")
            mesh = configured_mesh(cfg, src / "mesh.ply", out_dir / variant / slug)
            _, poses = read_poses_txt(src / "poses.txt")
            ev = pipeline.evaluate_against_ct(info.root, prep.seq, mesh, poses, out_dir / variant / slug / "evaluation")
            rows.append(_row(raw, variant, ev, abs_rel[variant]))
        # The two ablations start from the same poses and left-out frames as `full`'s last stage did
        if start != prev:
            prep = prepare_sequences(cfg, [sfm_seq], start)[0]
        start_id = None if start is None else file_id(start / "sequences" / slug / "summary.json")
        depth = std = colors = None
        for variant, changes in (("plain_fusion", {"fusion.name": "plain"}),
                                 ("no_failure_pgo", {"failure.enabled": False, "pgo.enabled": False})):
            vdir = out_dir / variant / slug
            _reset_if_other_source(vdir, {**seq_source, "previous": start_id})
            if not (vdir / "summary.json").is_file() and depth is None:
                depth, std, colors = pipeline.infer_depth(module, prep.seq, prep.cache)
            pipeline.refine_sequence(_variant_cfg(cfg, **changes), prep.seq, prep.cache, depth, std, colors,
                                     None if variant == "no_failure_pgo" else prep.excluded, vdir)
            _, poses = read_poses_txt(vdir / "poses.txt")
            rows.append(_row(raw, variant, pipeline.evaluate_against_ct(info.root, prep.seq,
                                                                  configured_mesh(cfg, vdir / "mesh.ply", vdir), poses,
                                                                  vdir / "evaluation"), abs_rel["full"]))
        if (cfg.get("adapt") or {}).get("enabled", True):
            _reset_if_other_source(out_dir / "adapted" / slug, seq_source, keep=("adaptation",))
            rows.append(run_adapted(cfg, module, info.root, sfm_seq, out_dir / "adapted" / slug))
        gdir = out_dir / "gt_upper_bound" / slug
        _reset_if_other_source(gdir, {"checkpoint": None, "settings": {"fusion": settings["fusion"]}})
        mesh = configured_mesh(cfg, fuse_ground_truth(cfg, info.root, raw, gdir / "mesh.ply"), gdir)
        rows.append(_row(raw, "gt_upper_bound", pipeline.evaluate_against_ct(info.root, raw, mesh, gt.cam_from_world,
                                                                       gdir / "evaluation")))
    return rows


def stage_start(fold_dir: Path, it: int, settings: dict, out_root: Path) -> Path | None:
    """The iteration dir whose ``sequences/<slug>`` the end-of-iteration stage of iteration ``it`` starts from
    when stages are made again with ``settings`` (:func:`refuse_iteration`): iteration ``it - 1`` as trained, or
    as made again into ``out_root`` when its recorded settings differ.  None for iteration 0."""
    if it == 0:
        return None
    trained = Path(fold_dir) / f"iteration={it - 1}"
    return Path(out_root) / trained.name if settings_diff(recorded_settings(trained), settings) else trained


def refuse_iteration(cfg: DictConfig, info, fold_dir: Path, it: int, sfm_seq, out_root: Path,
                     why: list[str]) -> dict:
    """The held-out sequence's end-of-iteration stage of ``fold_dir/iteration=<it>`` run again, from that
    iteration's network but with the settings of ``cfg``: for a fold trained before a fusion / failure / PGO
    setting changed.  A stage starts from the previous iteration's poses and left-out frames, which those
    settings decide as well, so every earlier iteration whose recorded settings differ is run again first, in
    order, each from its own network (the training run's outputs stand for the iterations that match).  The
    networks themselves were trained with the old settings; the table says which rows were made this way.

    Writes ``out_root/iteration=<k>/sequences/<slug>/`` for the stages it runs (the layout the SfM rerun of
    repeated failures reads its previous report from; where the previous iteration stands as trained, its
    report is copied there) and returns the CT evaluation of iteration ``it``'s."""
    from endorecon.tasks.reconstruct import load_module
    from endorecon.tasks.train import prepare_sequences

    slug = pipeline._slug(sfm_seq.name)
    settings = refine_settings(cfg)
    for k in range(it + 1):
        it_dir = Path(fold_dir) / f"iteration={k}"
        if k < it and not settings_diff(recorded_settings(it_dir), settings):
            continue  # this iteration stands as trained
        vdir = Path(out_root) / f"iteration={k}" / "sequences" / slug
        ckpt = it_dir / "checkpoints" / "last.ckpt"
        src = stage_start(fold_dir, k, settings, out_root)  # the previous stage's iteration dir
        prev_seq = None if src is None else src / "sequences" / slug
        # the previous stage's source too: a stage made after another one of iteration k-1 is made again
        _reset_if_other_source(vdir, {"checkpoint": file_id(ckpt), "settings": settings,
                                      "sfm": sfm_fingerprint(sfm_seq),
                                      "previous": None if prev_seq is None else file_id(prev_seq / "summary.json")})
        if not (vdir / "summary.json").is_file():
            log.info("%s: %s ran with other settings (%s); its last stage again into %s", sfm_seq.name, it_dir,
                     "; ".join(why), vdir)
            if src is not None and src.parent == Path(fold_dir) and (prev_seq / "failures.csv").is_file():
                # a stage standing as trained
                dst = Path(out_root) / f"iteration={k - 1}" / "sequences" / slug / "failures.csv"
                with atomic_path(dst) as tmp:
                    shutil.copyfile(prev_seq / "failures.csv", tmp)
            prep = prepare_sequences(cfg, [sfm_seq], src)[0]
            module, _ = load_module(ckpt)
            depth, std, colors = pipeline.infer_depth(module, prep.seq, prep.cache)
            pipeline.refine_sequence(cfg, prep.seq, prep.cache, depth, std, colors, prep.excluded, vdir)
    _, poses = read_poses_txt(vdir / "poses.txt")
    return pipeline.evaluate_against_ct(info.root, sfm_seq, configured_mesh(cfg, vdir / "mesh.ply", vdir), poses,
                                        vdir / "evaluation")


def run_adapted(cfg: DictConfig, module, data_root: Path, sfm_seq, out_dir: Path) -> dict:
    """The ``adapted`` variant of one held-out sequence: what ``reconstruct.py`` does with a new video.

    A copy of ``module`` is adapted to the sequence (SfM poses and sparse maps, no simulated depth, no
    exclusions), its depth is scored against GT depth (``depth_metrics.json``), refined and fused from
    the SfM poses, and the mesh registered to the CT.  Each step is skipped when its output exists."""
    from endorecon.tasks import adapt
    from endorecon.tasks.train import prepare_sequences

    opts = adapt._options(cfg.get("adapt"))
    if not opts["enabled"]:
        raise InputError("the adapted variant needs adapt.enabled=true", fix="drop adapt.enabled=false")
    out_dir = Path(out_dir)
    base = prepare_sequences(cfg, [sfm_seq], None)[0]
    metrics_path = out_dir / "depth_metrics.json"
    if metrics_path.is_file() and json.loads(metrics_path.read_text()).get("options") != opts:
        log.info("%s was made with other adapt options: running it again", out_dir)
        _empty_dir(out_dir, keep=("source.json",))  # which checkpoint and settings: those have not changed
    if not ((out_dir / "summary.json").is_file() and metrics_path.is_file()):
        net = copy.deepcopy(module)
        stamp = json.dumps({"fold": int(cfg.fold), "sequence": base.seq.name, "hw": [base.seq.height, base.seq.width]})
        _, info, _ = adapt.run(cfg.get("adapt"), net, cfg.data, [base], out_dir / "adaptation", stamp)
        depth, std, colors = pipeline.infer_depth(net, base.seq, base.cache)
        uncapped, capped = pipeline.evaluate_depth_with_cap(data_root, base.seq, depth, std,
                                                            cfg.bootstrap.get("depth_cap_mm"))
        pipeline.refine_sequence(cfg, base.seq, base.cache, depth, std, colors, None, out_dir)
        atomic_write_text(metrics_path, json.dumps({"depth_evaluation": uncapped, "depth_evaluation_capped": capped,
                                                    "adaptation": info, "options": opts}, indent=2) + "\n")
    dm = json.loads(metrics_path.read_text())
    _, poses = read_poses_txt(out_dir / "poses.txt")
    ev = pipeline.evaluate_against_ct(data_root, base.seq, configured_mesh(cfg, out_dir / "mesh.ply", out_dir), poses,
                                      out_dir / "evaluation")
    return _row(sfm_seq, "adapted", ev, dm["depth_evaluation"]["abs_rel"])


def read_table(csv_path: Path) -> list[dict]:
    """The rows of a ``results.csv`` that :func:`write_table` wrote (numbers as floats; none if it is missing)."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        return []
    rows = []
    with open(csv_path, newline="") as f:
        for r in csv.DictReader(f):
            try:
                row = {"patient": int(r["patient"]), "sequence": r.get("sequence") or None, "variant": r["variant"]}
                row.update({k: float(r[k]) if r.get(k) else None for k in COLUMNS})
            except (KeyError, ValueError) as e:
                raise InputError(f"not a results table written by this version ({e})", csv_path,
                                 "delete it, or run every fold again") from e
            row["refused"] = r["refused"].split("; ") if r.get("refused") else []
            rows.append(row)
    return rows


def percent_floor(fraction: float | None) -> str:
    """A fraction as a percentage rounded down to 0.1 %: 100 % only when every point is under the bound (0.9952
    read "100%" beside a maximum over it)."""
    if fraction is None:
        return ""
    return f"{math.floor(1000 * float(fraction) + 1e-9) / 10:.1f}%"


def write_table(rows: list[dict], out_dir: Path) -> tuple[Path, Path]:
    """``results.csv`` and ``results.md``: one row per (patient, variant), then the mean over patients."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fields = ["patient", "sequence", "variant", *COLUMNS, "refused"]

    def cell(r, f):
        v = r.get(f)
        if f == "refused":  # the settings that differed from the training run's
            return "; ".join(v) if v else ""
        return "" if v is None else (repr(float(v)) if isinstance(v, float) else str(v))  # read back exactly by read_table

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")  # quotes what needs it (commas in settings or names)
    writer.writerow(fields)
    writer.writerows([cell(r, f) for f in fields] for r in rows)
    csv_path = atomic_write_text(out_dir / "results.csv", buf.getvalue())
    # a sequence column only where a patient has several held-out videos (the default has one each)
    several = len({(r["patient"], r["variant"]) for r in rows}) < len(rows)
    md = ["| patient | " + ("sequence | " if several else "") + "variant | mean (mm) | median (mm) | p95 (mm) | max (mm) "
          "| < 1 mm | CT covered (cm²) | depth AbsRel | mesh std ρ |",
          "| --- | " + ("--- | " if several else "") + "--- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]

    def fmt(r):
        ar = "" if r.get("abs_rel") is None else f"{r['abs_rel']:.3f}"
        rho = "" if r.get("std_residual_spearman") is None else f"{r['std_residual_spearman']:+.2f}"
        cov = "" if r.get("ct_covered_mm2") is None else f"{r['ct_covered_mm2'] / 100:.1f}"
        who = f"| {r['patient']} | " + (f"{r.get('sequence') or ''} | " if several else "")
        if r["mean_mm"] is None:
            return who + "{} | n/a | n/a | n/a | n/a | n/a | n/a | {} | |".format(r["variant"], ar)
        return who + "{} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {} | {} | {} | {} |".format(
            r["variant"] + ("*" if r.get("refused") else ""), r["mean_mm"], r["median_mm"], r["p95_mm"],
            r["max_mm"], percent_floor(r["frac_below_1mm"]), cov, ar, rho)

    md += [fmt(r) for r in rows]
    refused = sorted({d for r in rows for d in (r.get("refused") or [])})
    for v in VARIANTS:
        vals = [r for r in rows if r["variant"] == v and r["mean_mm"] is not None]
        if vals:
            # over patients: a patient's videos are averaged first, so that one with two videos counts once
            by_patient: dict = {}
            for r in vals:
                by_patient.setdefault(r["patient"], []).append(r)

            def over_patients(k):
                per = [[r[k] for r in rs] for rs in by_patient.values()]
                if any(x is None for p in per for x in p):
                    return None
                return float(np.mean([np.mean(p) for p in per]))

            mean = {k: over_patients(k) for k in COLUMNS}
            md.append(fmt({"patient": "**mean**", "variant": v, **mean}))
    if refused:
        md += ["", "\\* the iteration's training run used other settings (" + "; ".join(refused) + "): its last stage "
               "(fusion, failure detection, PGO) was run again from that iteration's network with the current ones, "
               "after the earlier iterations' stages, each from its own network; the networks were trained with the "
               "old settings."]
    md_path = atomic_write_text(out_dir / "results.md", "\n".join(md) + "\n")
    return csv_path, md_path

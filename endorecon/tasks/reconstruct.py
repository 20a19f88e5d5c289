"""The reconstruct task: a new video -> SfM -> adaptation -> depth + std -> failures -> PGO -> fusion -> mesh + report.

``python reconstruct.py input=<video | frames folder | sequence folder | original-format folder>
[intrinsics=<camera.json | fx fy cx cy file>] [mask=<png>] [ckpt=<checkpoint>]``

Stages, each writing into the run dir and skipped when its outputs exist (an
interrupted run resumes; a failed stage loses nothing already written)::

    input.json                     what the run dir is made from (the input's identity, K, the mask's digest):
                                   resuming with another input is an error naming it
    frames/ + decode.json          input: video decoded to PNG frames (video input only)
    mask.png                       the valid-pixel mask used (given or estimated from the dark border)
    sfm/                           SfM stage (endorecon.sfm.stage): model/, sequence.npz, attempts.json
    adaptation/                    test-time self-supervised adaptation (endorecon.tasks.adapt): adapted.ckpt,
                                   adapt.json (steps, seconds, the video's loss before/after); adapt.enabled=false
                                   skips it
    depth.npz                      network depth, std, colours at the network's resolution (+ stamp)
    reconstruction/                failure detection, dense PGO, adaptive fusion (pipeline.refine_sequence):
                                   mesh.ply, poses.txt, failures.csv, simulated_depth.npz, summary.json
    mesh.ply                       copy of reconstruction/mesh.ply (coloured, per-vertex std)
    report.md, depth_std.png, mesh_preview.png, timings.json

The checkpoint is checked before SfM, so a wrong one costs nothing.  The
network runs at about the pixel count it was trained at, on the mask's
bounding box, aspect kept, sides divisible by its stride.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import shutil
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from endorecon.data.sequence import Sequence, list_frames, load_sequence_folder, read_camera_json, read_mask, read_rgb
from endorecon.data.transforms import crop_sequence, resize_sequence
from endorecon.tasks import pipeline
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_dir, atomic_path, atomic_save_npz, atomic_write_text, file_id

log = logging.getLogger(__name__)

CKPT_FIX = "pass ckpt=<checkpoints/last.ckpt written by python train.py>"


# ------------------------------------------------------------------ input
def _sample(frames: list[Path], k: int = 8) -> list[Path]:
    return [frames[i] for i in sorted(set(np.linspace(0, len(frames) - 1, min(k, len(frames))).astype(int)))]


INPUT_RECORD = "input.json"


def _source_id(src: Path, cfg: DictConfig) -> dict:
    """What the run dir's frames come from: the video file (and the frame selection), or a digest of the
    folder's files (names, sizes, mtimes), so that a run dir is never resumed with another input."""
    if src.is_file():
        v = cfg.video
        return {"input": file_id(src), "video": {k: v.get(k) for k in ("start", "stride", "max_frames")}}
    h = hashlib.sha1()
    for p in sorted(q for q in src.rglob("*") if q.is_file() and len(q.relative_to(src).parts) <= 2):
        st = p.stat()
        h.update(f"{p.relative_to(src)} {st.st_size} {st.st_mtime_ns}\n".encode())
    return {"input": str(src.resolve()), "files": h.hexdigest()}


def _camera_id(K: np.ndarray, mask: np.ndarray) -> dict:
    return {"K": [round(float(v), 6) for v in np.asarray(K, np.float64).ravel()],
            "mask": hashlib.sha1(np.packbits(mask.astype(bool)).tobytes() + str(mask.shape).encode()).hexdigest()}


def _check_same_input(out: Path, key: str, now: dict) -> None:
    """Refuse to resume ``out`` when its record says it was made from another input (nothing is touched)."""
    path = out / INPUT_RECORD
    before = _read_json(path).get(key)
    if before is not None and before != now:
        what = {"source": "another video / frames folder (or other files in it, or another frame selection)",
                "camera": "other intrinsics or another mask"}[key]
        raise InputError(f"this run dir was made from {what}; resuming it would mix the two", path,
                         f"pass name=<a new name> for a new run dir, or delete {out} to start over")


def _record_input(out: Path, key: str, now: dict) -> None:
    """Add ``key`` to the run dir's input record when it is not there yet (a run dir from before the record
    starts being checked now)."""
    path = out / INPUT_RECORD
    record = _read_json(path)
    if key not in record:
        atomic_write_text(path, json.dumps({**record, key: now}, indent=2) + "\n")


def input_sequence(cfg: DictConfig, out: Path) -> Sequence:
    """The input as a :class:`Sequence` without poses (frames, pixel-centre K, mask), checked.

    Accepts a video file (decoded into ``out/frames``), a sequence folder
    (``frames/``, ``camera.json``, ``mask.png``), the original method's folder
    format (``camera_intrinsics_per_view``), or a plain folder of frames
    (then ``intrinsics=`` is required).  ``mask=`` overrides any mask; without
    one a plain input's mask is estimated from the dark border.
    """
    from endorecon.data.video import (
        VIDEO_SUFFIXES, check_intrinsics_fit, check_texture, estimate_mask, extract_frames, read_intrinsics,
    )

    if cfg.input is None:
        raise InputError("no input given", fix="pass input=<video file or frames folder>")
    src = Path(str(cfg.input))
    if not src.exists():
        raise InputError("input does not exist", src, "pass input=<video file or frames folder>")
    source_id = _source_id(src, cfg)
    _check_same_input(out, "source", source_id)  # before any decoding: frames/ may be another video's
    # recorded before decoding and the checks below, so that a run stopped by them is still checked next time
    _record_input(out, "source", source_id)
    K = mask = None
    k_path: Path | None = None
    if src.is_dir() and (src / "camera.json").is_file() and (src / "frames").is_dir():
        seq = load_sequence_folder(src)
        frames, K, mask, k_path, source = seq.frame_paths, seq.intrinsics, seq.mask, src / "camera.json", "sequence"
        if cfg.intrinsics is None:  # the folder's own camera must be of its frames' size
            _, kh, kw, _ = read_camera_json(k_path)
            fh, fw = read_rgb(frames[0]).shape[:2]
            if (kh, kw) != (fh, fw):
                raise InputError(f"camera.json is for {kw}x{kh} frames but the frames are {fw}x{fh}", k_path,
                                 "write the camera of the frames' resolution, or pass intrinsics=<file>")
    elif src.is_dir() and (src / "camera_intrinsics_per_view").is_file():
        from endorecon.data.original import load_original

        seq = load_original(src, sfm=False)  # SfM runs here again: its poses and points are not needed
        frames, K, mask, k_path, source = seq.frame_paths, seq.intrinsics, seq.mask, \
            src / "camera_intrinsics_per_view", "original"
    elif src.is_file() and src.suffix.lower() in VIDEO_SUFFIXES:
        v = cfg.video
        frames = extract_frames(src, out / "frames", stride=int(v.stride), max_frames=v.max_frames,
                                start=int(v.get("start", 0)), allow_truncated=bool(v.get("allow_truncated", False)))
        source = "video"
    elif src.is_dir():
        frames, source = list_frames(src), "frames"
    else:
        raise InputError(f"unsupported input type {src.suffix!r}", src,
                         f"pass a video ({', '.join(VIDEO_SUFFIXES)}) or a folder of frames")
    h, w = read_rgb(frames[0]).shape[:2]
    if cfg.intrinsics is not None:  # an explicit file wins over the folder's own
        k_path = Path(str(cfg.intrinsics))
        K = read_intrinsics(k_path, pixel_origin=str(cfg.intrinsics_pixel_origin))
        if k_path.suffix == ".json":
            _, kh, kw, _ = read_camera_json(k_path)
            if (kh, kw) != (h, w):
                raise InputError(f"camera.json is for {kw}x{kh} frames but the frames are {w}x{h}", k_path,
                                 "give intrinsics of the frames' resolution")
    if K is None:
        raise InputError("no intrinsics given (self-calibration fails on endoscopy)", src,
                         "pass intrinsics=<camera.json or a text file with 'fx fy cx cy'> (add "
                         "intrinsics_pixel_origin=center if (cx, cy) count from the first pixel's centre)")
    check_intrinsics_fit(K, h, w, k_path)
    sample = [read_rgb(p, expect_hw=(h, w)) for p in _sample(frames)]
    if cfg.mask is not None:
        mask = read_mask(cfg.mask, expect_hw=(h, w))
    elif mask is None:
        mask = estimate_mask(sample)
    elif mask.shape != (h, w):
        raise InputError(f"the folder's mask is {mask.shape[1]}x{mask.shape[0]} but the frames are {w}x{h}",
                         src, "give a mask of the frames' size (mask=<png>)")
    check_texture(sample, mask, float(cfg.input_checks.min_texture), frames[0].parent)
    camera_id = _camera_id(K, mask)
    _check_same_input(out, "camera", camera_id)
    if not (out / "mask.png").is_file():
        from PIL import Image

        with atomic_path(out / "mask.png") as tmp:
            Image.fromarray(mask.astype(np.uint8) * 255).save(tmp)
    _record_input(out, "camera", camera_id)
    return Sequence(name=src.stem if src.is_file() else src.name, frame_paths=frames, intrinsics=K, height=h,
                    width=w, mask=mask, source=source)


# ------------------------------------------------------------------ model
def load_module(ckpt: str | Path):
    """A :class:`endorecon.module.DepthModule` from a ``train.py`` checkpoint, in eval mode on the CPU,
    and the (H, W) it was trained at (None if the checkpoint does not tell).

    The network is built from the checkpoint's own ``hyper_parameters.model``;
    weights that do not fit it (another model config, edited hparams, another
    kind of checkpoint) are an :class:`InputError` naming the mismatch.
    """
    from endorecon.module import DepthModule

    ckpt = Path(str(ckpt))
    if not ckpt.is_file():
        raise InputError("checkpoint does not exist", ckpt, "train first (python train.py) or " + CKPT_FIX)
    try:
        raw = torch.load(ckpt, map_location="cpu", weights_only=False)
    except Exception as e:  # pickle, zip and torch errors all mean "not a checkpoint"
        raise InputError(f"not a PyTorch checkpoint ({type(e).__name__}: {str(e)[:200]})", ckpt, CKPT_FIX) from e
    hp = raw.get("hyper_parameters") if isinstance(raw, dict) else None
    if not isinstance(raw, dict) or "state_dict" not in raw or not isinstance(hp, dict) or "model" not in hp:
        raise InputError("not a depth-model checkpoint of train.py (no state_dict / hyper_parameters.model)", ckpt,
                         CKPT_FIX)
    try:
        module = DepthModule(hp["model"], hp.get("loss"))
    except Exception as e:  # hydra instantiate errors come in many types
        raise InputError(f"its model config cannot be built ({type(e).__name__}: {str(e)[:300]})", ckpt,
                         CKPT_FIX) from e
    problems = _state_dict_mismatch(module.state_dict(), raw["state_dict"])
    if problems:
        raise InputError(f"the weights do not fit the network of the checkpoint's model config "
                         f"(net: {_net_summary(hp['model'])}): {problems}", ckpt,
                         "use the checkpoint together with the config it was trained with; " + CKPT_FIX)
    module.load_state_dict(raw["state_dict"])
    return module.eval(), _training_hw(raw, ckpt)


def _net_summary(model_cfg: dict) -> str:
    net = dict(model_cfg.get("net", {}))
    keys = ("_target_", "first_conv_channels", "growth_rate", "down_layers", "bottleneck_layers")
    return ", ".join(f"{k}={net[k]}" for k in keys if k in net)


def _state_dict_mismatch(expected: dict, got: dict) -> str:
    """'' when ``got`` fits ``expected`` (same keys and shapes), else a short description."""
    missing = [k for k in expected if k not in got]
    unexpected = [k for k in got if k not in expected]
    shapes = [(k, tuple(got[k].shape), tuple(expected[k].shape)) for k in expected
              if k in got and hasattr(got[k], "shape") and tuple(got[k].shape) != tuple(expected[k].shape)]
    parts = []
    if missing:
        parts.append(f"{len(missing)} missing tensor(s) (e.g. {missing[0]})")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected tensor(s) (e.g. {unexpected[0]})")
    if shapes:
        k, a, b = shapes[0]
        parts.append(f"{len(shapes)} shape mismatch(es) (e.g. {k}: {a} in the file, {b} in the network)")
    return "; ".join(parts)


def _training_hw(raw: dict, ckpt: Path) -> tuple[int, int] | None:
    """The (H, W) the network was trained at: ``hyper_parameters.input_hw`` if recorded, else the training
    run's ``.hydra/config.yaml`` beside ``checkpoints/``, else None."""
    hw = raw["hyper_parameters"].get("input_hw")
    if hw:
        return int(hw[0]), int(hw[1])
    for cand in (ckpt.parent.parent / ".hydra" / "config.yaml", ckpt.parent / ".hydra" / "config.yaml"):
        if cand.is_file():
            try:
                data = OmegaConf.load(cand).get("data", {})
                return int(data["height"]), int(data["width"])
            except Exception:  # an unreadable config only loses the hint
                log.warning("could not read the training resolution from %s", cand)
    return None


def latest_checkpoint(cfg) -> Path:
    """The newest ``last.ckpt`` of a finished iteration under ``<output_root>/train`` (single runs and
    multiruns alike)."""
    train = Path(cfg.paths.output_root) / "train"
    cands = sorted((p for p in train.glob("**/iteration=*/checkpoints/last.ckpt")
                    if (p.parents[1] / "metrics.json").is_file()), key=lambda p: p.stat().st_mtime)
    if not cands:
        raise InputError(f"no checkpoint given and no finished iteration's last.ckpt under {train}",
                         fix="train first (python train.py) or " + CKPT_FIX)
    return cands[-1]


# ------------------------------------------------------------------ resolution
def network_size(box_hw: tuple[int, int], train_hw: tuple[int, int], multiple: int) -> tuple[int, int]:
    """(H, W) for the network: about the pixel count of ``train_hw`` at the aspect of ``box_hw``, sides multiples
    of ``multiple`` (the network's stride).  Of the neighbouring multiples, the pair with the least
    |log aspect error| + 0.5 |log area error| wins."""
    bh, bw = box_hw
    area = train_hw[0] * train_hw[1]
    h = math.sqrt(area * bh / bw)
    w = area / h

    def around(x: float) -> list[int]:
        lo = max(1, math.floor(x / multiple))
        return [multiple * k for k in (lo, lo + 1)]

    def cost(hw: tuple[int, int]) -> float:
        return abs(math.log((hw[0] / hw[1]) / (bh / bw))) + 0.5 * abs(math.log(hw[0] * hw[1] / area))

    return min(((a, b) for a in around(h) for b in around(w)), key=cost)


def network_sequence(sfm_seq: Sequence, module, train_hw: tuple[int, int] | None, cfg: DictConfig) -> Sequence:
    """``sfm_seq`` cropped to its mask's bounding box and resized for the network (K and mask follow)."""
    multiple = 2 ** int(getattr(module.net, "levels", 5))
    size = cfg.inference.size
    seq = sfm_seq
    if cfg.inference.crop_to_mask:
        rows, cols = np.flatnonzero(seq.mask.any(1)), np.flatnonzero(seq.mask.any(0))
        y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        if (y1 - y0, x1 - x0) != (seq.height, seq.width):
            seq = crop_sequence(seq, int(x0), int(y0), int(x1 - x0), int(y1 - y0))
    if size in (None, "auto"):
        train_hw = train_hw or (int(cfg.data.height), int(cfg.data.width))
        h, w = network_size((seq.height, seq.width), train_hw, multiple)
    else:
        h, w = int(size[0]), int(size[1])
        if h % multiple or w % multiple:
            raise InputError(f"inference.size {h}x{w} is not divisible by the network's stride {multiple}",
                             fix=f"pass inference.size=[H,W] with multiples of {multiple}, or auto")
    return resize_sequence(seq, h, w)


# ------------------------------------------------------------------ stages
def _stamp(ckpt: Path, seq: Sequence) -> str:
    """What the depth maps depend on: the checkpoint file, the frames' size, window and count, and the SfM
    model (the Depth Scaling Layer scales depth to its sparse points; SfM made again is another scale)."""
    from endorecon.data.sequence import sfm_fingerprint

    return json.dumps(dict(ckpt=file_id(ckpt), hw=[seq.height, seq.width], window=list(seq.native_window or []),
                           frames=len(seq), sfm=sfm_fingerprint(seq)), sort_keys=True)


def infer_stage(module, seq: Sequence, cache, stamp: str, out: Path):
    """Depth and std of the registered frames, cached in ``out/depth.npz`` (recomputed if the stamp changed).

    Returns (depth (N,1,H,W), std (N,1,H,W), colors (N,H,W,3), skipped)."""
    path = out / "depth.npz"
    if path.is_file():
        try:
            z = np.load(path)
            if str(z["stamp"]) == stamp:
                return torch.from_numpy(z["depth"]), torch.from_numpy(z["std"]), z["colors"], True
            log.info("depth.npz was made with another checkpoint or resolution: inferring again")
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            log.warning("unreadable %s (%s): inferring again", path, e)
    registered = np.flatnonzero(seq.registered).tolist()
    depth, std, colors = pipeline.infer_depth(module, seq, cache, frames=registered)
    atomic_save_npz(path, depth=depth.numpy(), std=std.numpy(), colors=colors, stamp=np.array(stamp))
    return depth, std, colors, False


def run(cfg: DictConfig) -> Path:
    """Run (or resume) every stage; returns the run dir."""
    from endorecon.failure import check_low_thresholds

    check_low_thresholds(cfg.failure.get("low_thresholds"), cfg.failure.get("thresholds"))  # before any stage
    out = Path(cfg.paths.run_dir)
    out.mkdir(parents=True, exist_ok=True)
    old = _read_json(out / "timings.json").get("stages", {})
    stages: dict[str, dict] = {}

    def timed(name: str, t0: float, skipped: bool = False) -> None:
        now = time.perf_counter() - t0
        # a skipped stage keeps the time it took when it ran (None: not recorded, not counted as ~0 s)
        stages[name] = dict(seconds=old.get(name, {}).get("seconds") if skipped else now, skipped=skipped,
                            run_seconds=now)
        # written after every stage, so that a run stopped later still leaves the times of what it finished
        atomic_write_text(out / "timings.json", json.dumps(dict(stages={**old, **stages}, partial=True), indent=2)
                          + "\n")

    t0 = time.perf_counter()
    decoded_before = (out / "frames" / "decode.json").is_file()
    seq = input_sequence(cfg, out)
    timed("input", t0, skipped=decoded_before)
    log.info("%s: %d frames %dx%d (%s)", seq.name, len(seq), seq.width, seq.height, seq.source)

    t0 = time.perf_counter()
    ckpt = Path(str(cfg.ckpt)) if cfg.ckpt is not None else latest_checkpoint(cfg)
    module, train_hw = load_module(ckpt)
    timed("load model", t0)

    from endorecon.sfm.stage import is_complete as sfm_complete
    from endorecon.sfm.stage import load_result
    from endorecon.sfm.stage import run as sfm_run

    t0 = time.perf_counter()
    sfm_done = sfm_complete(cfg.sfm, seq, out / "sfm")
    sfm_run(cfg.sfm, seq, out / "sfm")
    sfm_seq = load_result(out / "sfm")
    timed("sfm", t0, skipped=sfm_done)
    log.info("SfM registered %d/%d frames", int(sfm_seq.registered.sum()), len(sfm_seq))

    t0 = time.perf_counter()
    small = network_sequence(sfm_seq, module, train_hw, cfg)
    from endorecon.data.sparse import build_sparse_cache

    cache = build_sparse_cache(small)
    timed("sparse maps", t0)

    # Test-time self-supervised adaptation on this video (endorecon/tasks/adapt.py); the depth maps are
    # then stamped with the adapted checkpoint, so a new adaptation means a new inference.
    from endorecon.data.datamodule import PreparedSequence
    from endorecon.tasks import adapt

    t0 = time.perf_counter()
    adapted, adapt_info, skipped = adapt.run(cfg.get("adapt"), module, cfg.get("data"),
                                             [PreparedSequence(seq=small, cache=cache)], out / "adaptation",
                                             _stamp(ckpt, small))
    if adapted is not None:
        timed("adaptation", t0, skipped=skipped)

    t0 = time.perf_counter()
    stamp = _stamp(adapted or ckpt, small)
    depth, std, colors, skipped = infer_stage(module, small, cache, stamp, out)
    timed("inference", t0, skipped=skipped)
    log.info("depth + std at %dx%d (network input)", small.width, small.height)

    t0 = time.perf_counter()
    rec = out / "reconstruction"
    # the depth maps and the fusion / failure / PGO settings that reconstruction/ is made from
    rec_stamp = json.dumps({"depth": stamp, "settings": pipeline.refine_settings(cfg)}, sort_keys=True)
    done = (rec / "summary.json").is_file()
    stale = done and _read_json(rec / "summary.json").get("stamp") != rec_stamp
    refined_before = done and not stale
    if stale:
        log.info("reconstruction/ was made from other depth maps or settings: running it again")
    # a stale one is made again beside the old one, which is replaced only once the new one is complete
    with atomic_dir(rec) if stale else contextlib.nullcontext(rec) as rec_dir:
        summary = pipeline.refine_sequence(cfg, small, cache, depth, std, colors, np.zeros(len(small), bool), rec_dir)
        if summary.get("stamp") != rec_stamp:
            summary["stamp"] = rec_stamp
            atomic_write_text(rec_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    timed("failure detection + PGO + fusion", t0, skipped=refined_before)
    with atomic_path(out / "mesh.ply") as tmp:
        shutil.copyfile(rec / "mesh.ply", tmp)

    t0 = time.perf_counter()
    report = write_report(out, small, summary, depth, std, colors, stages, ckpt, cfg, adapt_info)
    log.info("mesh: %s\nreport: %s", out / "mesh.ply", report)
    return out


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        return {}


# ------------------------------------------------------------------ report
def save_depth_std_png(path: Path, seq: Sequence, depth, std, colors, n: int = 4) -> Path:
    """Frames, depth and std of ``n`` frames spread over the sequence (registered frames only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reg = np.flatnonzero(seq.registered)
    picks = reg[np.unique(np.linspace(0, len(reg) - 1, min(n, len(reg))).astype(int))]
    fig, axes = plt.subplots(3, len(picks), figsize=(2.6 * len(picks) + 0.6, 2.6 * 3 * seq.height / seq.width + 0.8),
                             squeeze=False)
    m = seq.mask
    dv = depth[reg, 0].numpy()[:, m]
    sv = std[reg, 0].numpy()[:, m]
    dlim = np.percentile(dv, [1, 99]) if dv.size else (0, 1)
    slim = np.percentile(sv, [1, 99]) if sv.size else (0, 1)
    for c, i in enumerate(picks):
        axes[0, c].imshow(colors[i])
        axes[0, c].set_title(f"frame {i}", fontsize=9)
        im_d = axes[1, c].imshow(np.where(m, depth[i, 0].numpy(), np.nan), cmap="turbo", vmin=dlim[0], vmax=dlim[1])
        im_s = axes[2, c].imshow(np.where(m, std[i, 0].numpy(), np.nan), cmap="magma", vmin=slim[0], vmax=slim[1])
        for r in range(3):
            axes[r, c].set_axis_off()
    fig.colorbar(im_d, ax=axes[1].tolist(), fraction=0.03, label="depth (SfM units)")
    fig.colorbar(im_s, ax=axes[2].tolist(), fraction=0.03, label="std (SfM units)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return path


def write_report(out: Path, seq: Sequence, summary: dict, depth, std, colors, stages: dict, ckpt,
                 cfg: DictConfig | None = None, adapt_info: dict | None = None) -> Path:
    """``report.md`` with per-stage timings, flagged frames, and PNGs (depth/std samples, mesh preview)."""
    t0 = time.perf_counter()
    save_depth_std_png(out / "depth_std.png", seq, depth, std, colors)
    preview_ok = True
    try:
        from endorecon.evaluation.plots import render_mesh_preview

        render_mesh_preview(out / "mesh.ply", out / "mesh_preview.png", K=seq.intrinsics,
                            cam_from_world=seq.cam_from_world, height=seq.height, width=seq.width,
                            units="SfM units" if seq.units == "sfm" else seq.units)
    except Exception as e:  # a missing preview must not hide the mesh itself
        preview_ok = False
        log.warning("mesh preview failed: %s", e)
    stages["report"] = dict(seconds=time.perf_counter() - t0, skipped=False, run_seconds=time.perf_counter() - t0)
    sub = summary.get("times", {})
    total = sum(s["seconds"] for s in stages.values() if s["seconds"] is not None)
    now = sum(s["run_seconds"] for s in stages.values())
    rows = []
    failure_off = cfg is not None and not (cfg.get("failure") or {}).get("enabled", True)
    for name, s in stages.items():
        note = "done earlier (skipped)" if s["skipped"] else ""
        if s["seconds"] is None:
            rows.append(f"| {name} | n/a | done earlier (skipped), its time was not recorded: not in the total |")
            continue
        rows.append(f"| {name} | {s['seconds']:.1f} | {note} |")
        if name.startswith("failure"):
            labels = dict(fusion_s="fusion + simulated depth", failure_s="failure detection", pgo_s="dense PGO",
                          resfm_s="SfM rerun of flagged ranges", fusion2_s="fusion again + mesh")
            off = {"failure_s", "resfm_s"} if failure_off else set()  # metrics computed, nothing flagged
            rows += [f"| &nbsp;&nbsp;{labels.get(k, k)} | {v:.1f} | {'off: not acted on' if k in off else ''} |"
                     for k, v in sub.items()]
    mesh_info = _mesh_info(out / "mesh.ply")
    lines = [
        f"# Reconstruction of {seq.name}",
        "",
        f"- frames: {len(seq)}, registered by SfM: {summary['registered']}, fused: {summary['fused']}",
        ("- failure detection: off (failure.enabled=false)" if failure_off else
         f"- flagged by failure detection: {summary['n_flagged']} {summary['flagged']}")
        + (f" (of them next to a flagged frame, at a low threshold: {summary['flagged_low']})"
           if summary.get("flagged_low") else "")
        + (f"; left out of fusion with their neighbours: {summary['excluded']}" if summary.get("excluded") else "")
        + ("; **every frame was flagged, so all registered frames were fused** (check the failure thresholds "
           "and `reconstruction/failures.csv`)" if summary.get("all_flagged_fused") else ""),
        f"- network input: {seq.width}x{seq.height} (window {seq.native_window} of the frames)",
        f"- checkpoint: `{ckpt}`",
        f"- test-time adaptation: {_adapt_line(adapt_info)}",
        f"- mesh: `mesh.ply` ({mesh_info}; coloured{', per-vertex std' if _mesh_has_std(out / 'mesh.ply') else ', no std (plain TSDF fusion)'}), refined poses: `reconstruction/poses.txt`, "
        f"failure metrics: `reconstruction/failures.csv`",
        f"- dense PGO: {_pgo_line(summary.get('pgo'))}",
        f"- free-space check: {_free_space_line(summary.get('free_space'))}",
        f"- uncertainty trim: {_uncertain_line(summary.get('uncertain'), (cfg.get('fusion') or {}).get('name') if cfg is not None else None)}",
        f"- nearest-view check: {_far_only_line(summary.get('far_only'))}",
        "",
        "| stage | time (s) | |",
        "| --- | ---: | --- |",
        *rows,
        f"| **total** | **{total:.1f}** | this run: {now:.1f} s |",
        "",
        "![depth and std](depth_std.png)",
        "",
    ]
    if preview_ok:
        lines += ["![mesh preview](mesh_preview.png)", ""]
    atomic_write_text(out / "report.md", "\n".join(lines))
    atomic_write_text(out / "timings.json", json.dumps(dict(stages=stages, refine=sub, total_s=total,
                                                            this_run_s=now), indent=2) + "\n")
    return out / "report.md"


def _removed(info: dict, why: str) -> str:
    """``"<n> of <m> triangles (<p> %) removed: <why>"`` of a saved-mesh check's record."""
    share = info["removed"] / info["triangles"] if info.get("triangles") else 0.0
    return f"{info['removed']} of {info['triangles']} triangles ({100 * share:.1f} %) removed: {why}"


def _free_space_line(fs) -> str:
    if not isinstance(fs, dict):
        return "off (fusion.free_space_max_fraction=null) or not recorded"
    return _removed(fs, f"surface that most of the {fs['frames']} fused frames see through")


def _far_only_line(f) -> str:
    if not isinstance(f, dict):
        return "off (fusion.max_nearest_view_ratio=null) or not recorded"
    return _removed(f, f"surface no fused frame sees nearer than {f.get('ratio', float('nan')):.3g}x their median depth")


def _uncertain_line(u, fusion_name: str | None = None) -> str:
    if not isinstance(u, dict):
        if fusion_name == "plain":
            return "none (plain TSDF fusion carries no std)"
        return "off (fusion.max_std_ratio=null): all fused surface kept, its std in the mesh"
    return _removed(u, f"fused std over {u.get('ratio', float('nan')):.3g}x the mesh's median")


def _pgo_line(pgo: dict | None) -> str:
    if not pgo:
        return "off (pgo.enabled=false)"
    rot_med, rot_max = pgo.get("update_rotation_deg_median"), pgo.get("update_rotation_deg_max")
    tr_med, tr_max = pgo.get("update_translation_median"), pgo.get("update_translation_max")
    moved = ("no registered frame moved" if rot_max is None else
             f"pose updates {rot_med:.3g}° median / {rot_max:.3g}° max in rotation, "
             f"{tr_med:.3g} / {tr_max:.3g} in camera centre (SfM units)")
    return f"objective {pgo['loss_before']:.6g} -> {pgo['loss_after']:.6g}; {moved}"


def _adapt_line(info: dict | None) -> str:
    if not info:
        return "off (adapt.enabled=false)"
    if not info.get("steps"):
        return "no step (adapt.epochs=0): the checkpoint's weights"
    verdict = "kept" if info.get("kept") else "**not kept** (the loss did not go down; original weights used)"
    return (f"{info.get('steps', 0)} steps in {info.get('seconds', 0.0):.0f} s, the video's self-supervised loss "
            f"{info.get('loss_before', float('nan')):.4g} -> {info.get('loss_after', float('nan')):.4g}, {verdict} "
            f"(`adaptation/adapt.json`)")


def _mesh_has_std(path: Path) -> bool:
    from endorecon.fusion.ply import ply_header_lines

    try:
        return any(ln.split()[-1] == "std" for ln in ply_header_lines(path) if ln.startswith("property"))
    except (OSError, ValueError, IndexError):
        return False


def _mesh_info(path: Path) -> str:
    from endorecon.fusion.ply import ply_header_lines

    try:
        head = ply_header_lines(path)
        nv = next(int(ln.split()[-1]) for ln in head if ln.startswith("element vertex"))
        nf = next(int(ln.split()[-1]) for ln in head if ln.startswith("element face"))
        return f"{nv} vertices, {nf} triangles"
    except (OSError, StopIteration, ValueError):
        return "unreadable header"

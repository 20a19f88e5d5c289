"""The SfM stage: frames + known intrinsics + mask -> poses and clean sparse points.

``run(cfg_sfm, seq, out_dir)`` writes into ``out_dir``::

    images/000000.png ...      the frames at SfM resolution (downscaled copies)
    mask.png                   the SfM mask (eroded by ``mask_erode_px``)
    attempts/<k>_<name>/       one pycolmap run per hyperparameter set:
        database.db, sparse/   COLMAP's own output
        model/                 the largest model (binary)
        result.json            its numbers (registered frames, models, points, time)
    attempts.json              every attempt's numbers, the chosen one, cleaning and scale
    settings.json              the settings it was made with (other settings: made again, see run())
    model/                     the final model (binary COLMAP, at the input resolution, cleaned, normalised)
    sequence.npz               the final :class:`Sequence` (cam_from_world, clean points, visibility)

Work whose output exists is skipped, so an interrupted run resumes.

**Reruns.** Attempts follow the list ``cfg_sfm.attempts`` (conf/sfm/default.yaml): each entry
overrides COLMAP hyperparameters (SIFT peak threshold, number of features, sequential overlap,
initial pair, triangulation angles).  An attempt *passes* when the largest model registers at least
``min_registered`` of the frames, there is no other model of >= ``min_model_size`` frames, and it has
at least ``min_points`` points.  The stage stops at the first passing attempt; otherwise it keeps the
best (most frames registered, then fewest models, then most points) and raises :class:`SfMError`
listing every attempt and what to try — unless ``allow_partial`` is true, in which case the best
partial result is returned with the unregistered frames named in the log and in ``attempts.json``.
A result with no registered frame is never returned.

Cleaning and the global scale normalisation are documented in :mod:`endorecon.sfm.clean`: the world
is scaled so that the median sparse z-depth is 1 (factor in ``attempts.json``), ``units="sfm"``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from endorecon.data.sequence import Sequence
from endorecon.data.transforms import resize_sequence
from endorecon.sfm import colmap
from endorecon.sfm.clean import clean_sparse, normalize_scale
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_path, atomic_write_text, file_lock, remove_path

log = logging.getLogger(__name__)

DEFAULTS = dict(
    max_size=960,
    mask_erode_px=4,
    min_registered=0.9,
    min_points=100,
    min_model_size=3,
    num_threads=-1,
    colmap_verbose=False,
    allow_partial=False,
    clean=dict(
        min_track_length=3,
        max_reproj_error=2.0,
        visibility_window=5,
        max_depth_ratio=3.0,
        min_brightness=0.05,
        min_observations=2,
    ),
    attempts=[dict(name="default", peak_threshold=0.003, max_num_features=8192, overlap=10)],
)

HINTS = (
    "check that the frames show textured tissue (not black, blurred or saturated), that the mask marks the "
    "field of view white, and that the intrinsics match the frames; add attempts to conf/sfm/default.yaml "
    "(lower peak_threshold, larger overlap, smaller init_min_tri_angle), or set sfm.allow_partial=true to "
    "keep the largest partial model"
)


class SfMError(InputError):
    """SfM found no acceptable model: the message lists every attempt and what to try."""


def _cfg(cfg_sfm) -> dict:
    """Plain dict of the stage config with defaults filled in (accepts a DictConfig, a dict or None)."""
    if cfg_sfm is None:
        cfg = {}
    else:
        try:
            from omegaconf import OmegaConf

            cfg = OmegaConf.to_container(cfg_sfm, resolve=True) if OmegaConf.is_config(cfg_sfm) else dict(cfg_sfm)
        except ImportError:  # pragma: no cover
            cfg = dict(cfg_sfm)
    out = {**DEFAULTS, **cfg}
    out["clean"] = {**DEFAULTS["clean"], **(cfg.get("clean") or {})}
    if not out["attempts"]:
        raise InputError("sfm.attempts is empty", fix="list at least one hyperparameter set in conf/sfm/default.yaml")
    # ``seed`` seeds every attempt that has none of its own; each attempt's record then holds it, so a changed
    # seed runs the attempts again (and null changes nothing that was recorded before the key existed)
    seed = out.pop("seed", None)
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise InputError(f"sfm.seed must be an integer or null, got {seed!r}", fix="pass sfm.seed=0 (or null)")
        out["attempts"] = [{"seed": seed, **a} for a in out["attempts"]]
    return out


# ------------------------------------------------------------------ inputs
def _check_frames(seq: Sequence) -> tuple[int, int]:
    """All frame files exist, are images and have one size; returns that native size (H, W)."""
    if len(seq) < 3:
        raise InputError(f"SfM needs at least 3 frames, got {len(seq)}",
                         seq.frame_paths[0].parent if len(seq) else None, "pass a longer clip")
    sizes = {}
    for p in seq.frame_paths:
        if not p.is_file():
            raise InputError("frame file is missing", p, "restore the file or remove it from the sequence")
        try:
            with Image.open(p) as im:
                sizes.setdefault(im.size, p)
        except OSError as e:
            raise InputError(f"cannot read image ({e})", p, "re-export the frame or delete it") from e
    if len(sizes) > 1:
        desc = ", ".join(f"{w}x{h} (e.g. {p.name})" for (w, h), p in sizes.items())
        raise InputError(f"frames have different sizes: {desc}", seq.frame_paths[0].parent,
                         "all frames of a sequence must have the same size; re-export them at one size")
    (w, h), _ = sizes.popitem()
    if seq.native_window is None and (h, w) != (seq.height, seq.width):
        raise InputError(f"frames are {w}x{h} (WxH) but the sequence record says {seq.width}x{seq.height}",
                         seq.frame_paths[0], "fix camera.json / the intrinsics' image size")
    return h, w


def sfm_size(height: int, width: int, max_size: int) -> tuple[int, int]:
    """(height, width) for SfM: the longest side at most ``max_size`` (aspect kept)."""
    s = min(1.0, max_size / max(height, width)) if max_size and max_size > 0 else 1.0
    return max(1, int(round(height * s))), max(1, int(round(width * s)))


def _prepare_images(seq: Sequence, cfg: dict, out_dir: Path) -> tuple[Sequence, list[str]]:
    """Write SfM-resolution copies of the frames and the eroded mask; return the SfM-resolution sequence."""
    h, w = sfm_size(seq.height, seq.width, cfg["max_size"])
    small = resize_sequence(seq, h, w) if (h, w) != (seq.height, seq.width) else seq
    img_dir = out_dir / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    names = [f"{i:06d}.png" for i in range(len(seq))]
    for i, n in enumerate(names):
        if not (img_dir / n).is_file():
            with atomic_path(img_dir / n) as tmp:
                Image.fromarray(small.load_frame(i)).save(tmp)
    mask = small.mask
    if cfg["mask_erode_px"] > 0:
        # erode so that the rim of the field of view makes no keypoints; the image border is not a rim
        mask = ndimage.binary_erosion(mask, iterations=int(cfg["mask_erode_px"]), border_value=1)
    if not (out_dir / "mask.png").is_file():
        with atomic_path(out_dir / "mask.png") as tmp:
            Image.fromarray(mask.astype(np.uint8) * 255).save(tmp)
    sfm_seq = small.replace(frame_paths=[img_dir / n for n in names], native_window=None)
    return sfm_seq, names


# ------------------------------------------------------------------ attempts
def _attempt_dir(out_dir: Path, k: int, attempt: dict) -> Path:
    return out_dir / "attempts" / f"{k:02d}_{attempt.get('name', 'attempt')}"


def _run_attempt(sfm_seq: Sequence, names: list[str], cfg: dict, k: int, out_dir: Path) -> dict:
    """Run (or load) attempt k; returns its result dict."""
    attempt = cfg["attempts"][k]
    adir = _attempt_dir(out_dir, k, attempt)
    res_path = adir / "result.json"
    res = json.loads(res_path.read_text()) if res_path.is_file() else None
    if res is not None and (res.get("params") != attempt or res.get("frames") != len(names)):
        log.info("attempt %d: settings changed since the stored run; running it again", k)
        res = None
    if res is not None:
        # the checks may have changed since: the second-model count too (sfm.min_model_size)
        res["models"] = sum(int(n) >= int(cfg["min_model_size"]) for n in res.get("model_sizes", []))
        res["problems"] = _problems(res, cfg)
        res["passed"] = not res["problems"]
        log.info("attempt %d (%s): already done, %d/%d registered", k, res["name"], res["registered"], len(names))
        return res
    t0 = time.perf_counter()
    models, stats = colmap.run_mapping(
        out_dir / "images", names, out_dir / "mask.png", sfm_seq.intrinsics, attempt, adir / "colmap",
        num_threads=int(cfg["num_threads"]), verbose=bool(cfg["colmap_verbose"]),
    )
    seconds = time.perf_counter() - t0
    big = [m for m in models if m.num_reg_images() >= int(cfg["min_model_size"])]
    res = dict(
        index=k,
        name=attempt.get("name", f"attempt{k}"),
        params=attempt,
        registered=int(models[0].num_reg_images()) if models else 0,
        frames=len(names),
        models=len(big),
        model_sizes=[int(m.num_reg_images()) for m in models],
        points=int(models[0].num_points3D()) if models else 0,
        mean_reproj_error=float(models[0].compute_mean_reprojection_error()) if models else None,
        seconds=round(seconds, 3),
        **stats,
    )
    res["registered_fraction"] = res["registered"] / len(names)
    res["problems"] = _problems(res, cfg)
    res["passed"] = not res["problems"]
    if models:
        colmap.write_reconstruction(models[0], adir / "model")
    atomic_write_text(res_path, json.dumps(res, indent=2) + "\n")
    log.info(
        "attempt %d (%s): %d/%d frames registered, %d model(s) %s, %d points, %.0f features/frame, %.1f s%s",
        k, res["name"], res["registered"], len(names), res["models"], res["model_sizes"], res["points"],
        res["num_features"], seconds, "" if res["passed"] else " -> " + "; ".join(res["problems"]),
    )
    return res


def _problems(res: dict, cfg: dict) -> list[str]:
    p = []
    if res["registered_fraction"] < cfg["min_registered"]:
        p.append(f"registered {res['registered']}/{res['frames']} < {cfg['min_registered']:.0%}")
    if res["models"] > 1:
        p.append(f"{res['models']} disconnected models {res['model_sizes']}")
    if res["points"] < cfg["min_points"]:
        p.append(f"{res['points']} points < {cfg['min_points']}")
    return p


def _score(res: dict) -> tuple:
    return (res["registered"], -res["models"], res["points"])


def _unregistered_names(seq: Sequence, cam_from_world: np.ndarray) -> list[str]:
    reg = np.isfinite(cam_from_world).all(axis=(1, 2))
    return [seq.frame_paths[i].name for i in np.nonzero(~reg)[0]]


def _describe(results: list[dict]) -> str:
    return "\n".join(
        f"  attempt {r['index']} ({r['name']}): {r['registered']}/{r['frames']} registered, {r['models']} model(s) "
        f"{r['model_sizes']}, {r['points']} points, {r['num_features']:.0f} features/frame"
        + ("" if r["passed"] else " -- " + "; ".join(r["problems"]))
        for r in results
    )


def _solve(cfg: dict, seq: Sequence, out_dir: Path, attempt_ids: list[int], allow_partial: bool) -> Sequence:
    """Attempts in order until one passes; clean, normalise and write the result."""
    t_start = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    _check_frames(seq)
    sfm_seq, names = _prepare_images(seq, cfg, out_dir)
    log.info("SfM on %d frames at %dx%d (from %dx%d) in %s", len(seq), sfm_seq.width, sfm_seq.height,
             seq.width, seq.height, out_dir)
    results = []
    for k in attempt_ids:
        results.append(_run_attempt(sfm_seq, names, cfg, k, out_dir))
        if results[-1]["passed"]:
            break
    best = max(results, key=_score)
    summary = dict(frames=len(seq), sfm_size=[sfm_seq.height, sfm_seq.width], attempts=results,
                   chosen=best["index"], passed=best["passed"])
    if best["registered"] == 0 or (not best["passed"] and not allow_partial):
        summary["status"] = "failed"
        atomic_write_text(out_dir / "attempts.json", json.dumps(summary, indent=2) + "\n")
        raise SfMError(
            f"SfM found no acceptable model for {len(seq)} frames in {len(results)} attempt(s):\n"
            + _describe(results),
            seq.frame_paths[0].parent,
            HINTS,
        )

    rec = colmap.load_reconstruction(_attempt_dir(out_dir, best["index"], cfg["attempts"][best["index"]]) / "model")
    arr = colmap.reconstruction_arrays(rec, names)

    def load_gray(i: int) -> np.ndarray:
        with Image.open(sfm_seq.frame_paths[i]) as im:
            return np.asarray(im.convert("L"), dtype=np.float32) / 255.0

    pts, vis, cstats = clean_sparse(
        arr["cam_from_world"], sfm_seq.intrinsics, sfm_seq.mask, arr["points_xyz"], arr["visibility"],
        errors=arr["errors"], load_gray=load_gray, **cfg["clean"],
    )
    kept = cstats.pop("kept_index")
    T, pts, scale = normalize_scale(arr["cam_from_world"], pts, vis)
    result = seq.replace(
        cam_from_world=T, points_xyz=pts, visibility=vis, points_rgb=arr["points_rgb"][kept], units="sfm",
        source="colmap",
    )
    unregistered = _unregistered_names(seq, T)
    if unregistered:
        log.warning("%d frame(s) not registered: %s", len(unregistered), ", ".join(unregistered))
    log.info("cleaning: %s", cstats)
    log.info("scale normalisation: x%.6g (median sparse z-depth = 1)", scale)
    colmap.write_colmap_model(result, out_dir / "model")
    result.save(out_dir / "sequence.npz")
    summary.update(
        status="ok" if best["passed"] else "partial",
        unregistered=unregistered,
        clean=cstats,
        scale_factor=scale,
        seconds=round(time.perf_counter() - t_start, 3),
        seconds_per_frame=round((time.perf_counter() - t_start) / len(seq), 4),
    )
    atomic_write_text(out_dir / "attempts.json", json.dumps(summary, indent=2) + "\n")
    return result


# ------------------------------------------------------------------ public API
def run(cfg_sfm, seq: Sequence, out_dir: str | Path) -> Path:
    """Run the SfM stage (see the module docstring); skips it if ``out_dir`` holds a complete result.

    Args:
        cfg_sfm: the ``sfm`` config group (conf/sfm/default.yaml), a dict, or None for the defaults.
        seq: frames, intrinsics (pixel-centre) and mask; its poses and points are ignored.
        out_dir: the stage's folder.
    Returns:
        ``out_dir`` (read the result with :func:`load_result`).
    Raises:
        SfMError: no attempt gave an acceptable model (and ``allow_partial`` is false).
    """
    out_dir = Path(out_dir)
    cfg = _cfg(cfg_sfm)
    settings = _settings(cfg, seq)
    # jobs sharing a cache (folds run in parallel) take turns: two COLMAP runs on one database abort
    with file_lock(out_dir.parent / f".{out_dir.name}.lock"):
        kept = out_dir / ".other_settings"  # what other settings made, back in place if these fail
        if kept.is_dir():  # a run that set it aside was killed: the earlier result is still the one to keep
            _restore(out_dir, kept)
        _set_aside_other_settings(out_dir, settings, kept)
        if _has_result(out_dir):
            log.info("SfM: %s is complete, skipping", out_dir)
            return out_dir
        out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_dir / "settings.json", json.dumps(settings, indent=2, sort_keys=True) + "\n")
        try:
            _solve(cfg, _bare(seq), out_dir, list(range(len(cfg["attempts"]))), bool(cfg["allow_partial"]))
        except BaseException:
            if kept.is_dir():
                _restore(out_dir, kept)
                log.warning("SfM: the result made with the earlier settings is back in %s", out_dir)
            raise
        remove_path(kept)
    return out_dir


def _has_result(out_dir: Path) -> bool:
    return (out_dir / "sequence.npz").is_file() and (out_dir / "attempts.json").is_file()


def is_complete(cfg_sfm, seq: Sequence, out_dir: str | Path) -> bool:
    """Whether :func:`run` would skip: a complete result made with these settings (or with unrecorded ones)."""
    out_dir = Path(out_dir)
    if not _has_result(out_dir):
        return False
    recorded = _read_settings(out_dir)
    return recorded is None or _same_settings(recorded, _settings(_cfg(cfg_sfm), seq))


# What the SfM-resolution images and the COLMAP attempts are made from; the rest of the settings (cleaning, the
# acceptance checks, the attempt list, whose entries each attempt's result.json records) only needs the
# final steps made again.  Logging and threads change nothing that is kept.
def _settings(cfg: dict, seq: Sequence) -> dict:
    rest = {k: v for k, v in cfg.items() if k not in ("max_size", "mask_erode_px", "colmap_verbose", "num_threads")}
    return {"images": {"max_size": cfg["max_size"], "mask_erode_px": cfg["mask_erode_px"],
                       "frames": [len(seq), seq.height, seq.width],
                       "intrinsics": np.asarray(seq.intrinsics, dtype=float).round(9).tolist(),
                       "mask": _mask_digest(seq.mask), "frame_files": _frames_digest(seq)},
            "rest": json.loads(json.dumps(rest, sort_keys=True))}


def _mask_digest(mask: np.ndarray) -> str:
    m = np.asarray(mask, dtype=bool)
    return hashlib.sha1(f"{m.shape}".encode() + np.packbits(m).tobytes()).hexdigest()[:16]


def _frames_digest(seq: Sequence) -> str:
    """The frames' names, sizes and modification times (cheap for long videos): other frames written into the
    same folder make SfM again."""
    h = hashlib.sha1()
    for p in seq.frame_paths:
        try:
            st = Path(p).stat()
            h.update(f"{Path(p).name}:{st.st_size}:{st.st_mtime_ns};".encode())
        except OSError:  # a missing frame: _check_frames names it before SfM runs
            h.update(f"{Path(p).name}:missing;".encode())
    return h.hexdigest()[:16]


def _same_settings(recorded: dict, settings: dict) -> bool:
    """``recorded`` equals ``settings`` on what it recorded: a folder made before a key was recorded (the mask,
    the frames' bytes) is judged by the keys it has."""
    return recorded.get("rest") == settings["rest"] and _same_images(recorded, settings)


def _same_images(recorded: dict, settings: dict) -> bool:
    rec = recorded.get("images")
    return isinstance(rec, dict) and all(rec[k] == settings["images"].get(k) for k in rec)


def _read_settings(out_dir: Path) -> dict | None:
    try:
        return json.loads((out_dir / "settings.json").read_text())
    except (OSError, ValueError):
        return None


def _set_aside_other_settings(out_dir: Path, settings: dict, kept: Path) -> None:
    """Move what ``out_dir`` holds from other settings into ``kept`` (:func:`run` puts it back if these settings
    fail, and deletes it once they succeed), so that it is made again with these: the images and every attempt
    when the SfM size, mask erosion, mask, frames or intrinsics changed (COLMAP ran on other images), only the
    final result when cleaning or the checks did.  A folder without ``settings.json`` (made before it was
    recorded) is kept as it is; one made before a key was recorded is judged by those it has, and its
    ``settings.json`` gains the new keys."""
    recorded = _read_settings(out_dir)
    if recorded is None:
        return
    if _same_settings(recorded, settings):
        if recorded != settings:
            atomic_write_text(out_dir / "settings.json", json.dumps(settings, indent=2, sort_keys=True) + "\n")
        return
    stale = ["sequence.npz", "attempts.json", "model", "settings.json"]
    if not _same_images(recorded, settings):
        stale += ["images", "mask.png", "attempts"]
        log.warning("SfM: %s was made from other images (size, mask, erosion, frames or intrinsics); running SfM "
                    "again", out_dir)
    else:
        log.info("SfM: %s was made with other cleaning or checks; choosing and cleaning again", out_dir)
    kept.mkdir(parents=True)
    for name in stale:
        if (out_dir / name).exists():
            os.replace(out_dir / name, kept / name)


def _restore(out_dir: Path, kept: Path) -> None:
    """Put back what :func:`_set_aside_other_settings` moved into ``kept``, over what the failed run made."""
    for p in kept.iterdir():
        remove_path(out_dir / p.name)
        os.replace(p, out_dir / p.name)
    remove_path(kept)


def load_result(out_dir: str | Path) -> Sequence:
    """The sequence written by :func:`run` (``out_dir/sequence.npz``)."""
    return Sequence.load(Path(out_dir) / "sequence.npz")


def rerun(cfg_sfm, seq: Sequence, segment: tuple[int, int], attempt: int, out_dir: str | Path) -> Sequence:
    """SfM on the frames ``segment = (first, last)`` (inclusive) with hyperparameter set ``attempt``.

    For the failure-detection stage: a frame range that keeps failing is solved again on its own.
    The result is returned even if it fails the stage's checks (the caller decides), but never with
    no registered frame.  Frame indices in the result are relative to ``first``; the world frame
    and scale are the segment's own (median sparse depth 1).  Skips work already in ``out_dir``.
    """
    cfg = _cfg(cfg_sfm)
    first, last = int(segment[0]), int(segment[1])
    if not (0 <= first < last < len(seq)):
        raise InputError(f"segment {segment} is not a frame range of the {len(seq)}-frame sequence")
    if not (0 <= attempt < len(cfg["attempts"])):
        raise InputError(f"attempt {attempt} does not exist; sfm.attempts has {len(cfg['attempts'])} entries")
    out_dir = Path(out_dir)
    if (out_dir / "sequence.npz").is_file():
        return load_result(out_dir)
    sub = _bare(seq).replace(frame_paths=seq.frame_paths[first : last + 1], cam_from_world=None)
    return _solve(cfg, sub, out_dir, [attempt], allow_partial=True)


def _bare(seq: Sequence) -> Sequence:
    return seq.replace(cam_from_world=None, points_xyz=None, visibility=None, points_rgb=None)

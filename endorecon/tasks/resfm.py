"""SfM reruns of frame ranges that failure detection flags in two consecutive iterations.

The method: "a frame range flagged again in the next iteration triggers the SfM
stage's rerun with other hyperparameters for that range".  For every such range
:func:`rerun_repeated_failures`

1. pads it by ``pad`` frames each side (clipped to the sequence) and runs
   :func:`endorecon.sfm.stage.rerun` on that segment with the next hyperparameter
   set (``1 + earlier reruns of the range``, capped at the last entry of
   ``sfm.attempts``);
2. aligns the segment's own world (own scale) to the current one with a Sim(3)
   fitted on the *anchor* frames: pad frames that are not flagged/excluded and are
   registered in both.  Camera centres alone leave the rotation about the
   trajectory undetermined when the camera moves along a line (typical in a
   nasal cavity), so each anchor also contributes its three camera axes as
   points at a length proportional to the anchors' spread (the same length in
   both worlds up to the scale being estimated; see :func:`_anchor_points`);
3. replaces the poses of the replaced frames with the aligned segment poses: the
   range, from its first to its last flagged checked frame (the frames between
   them, checked or not, lie in the failed span), widened by ``replace_radius``
   (default ``failure.exclude_radius`` or ``interval // 2``: the frames excluded
   from fusion around a flagged frame).

Pose conversion: with x_cam = R_c x_seg + t_c (segment world) and
x_w = s R x_seg + t, camera coordinates in current-world units are
s x_cam = (R_c R^T) x_w + (s t_c - R_c R^T t): see :func:`align_segment_poses`.

Everything is recorded in ``out_dir/resfm.json`` (ranges, attempts, anchors,
per-frame pose change, and why a range was skipped).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from endorecon.data.sequence import Sequence
from endorecon.geometry import camera_centers, umeyama
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_write_text

log = logging.getLogger(__name__)

DEFAULTS = dict(enabled=True, pad=5, first_attempt=1, min_anchor_frames=3, replace_radius=None)


def rerun_cfg(cfg) -> dict:
    """``cfg.failure.rerun`` as a plain dict with defaults filled in (missing block: the defaults)."""
    block = None
    fail = cfg.get("failure") if cfg is not None else None
    if fail is not None:
        block = fail.get("rerun")
    if block is not None and OmegaConf.is_config(block):
        block = OmegaConf.to_container(block, resolve=True)
    out = {**DEFAULTS, **(block or {})}
    for key in ("pad", "first_attempt", "min_anchor_frames"):
        if int(out[key]) < 0:
            raise InputError(f"failure.rerun.{key} must be >= 0, got {out[key]}", fix="set it in conf/failure/default.yaml")
    if int(out["min_anchor_frames"]) < 2:
        raise InputError("failure.rerun.min_anchor_frames must be >= 2 (a similarity needs two distinct centres)",
                         fix="set it in conf/failure/default.yaml")
    return out


# ------------------------------------------------------------------ geometry
def align_segment_poses(seg_cam_from_world: np.ndarray, scale: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Segment poses expressed in the current world, for x_w = scale R x_seg + t.

    Args:
        seg_cam_from_world: (M, 4, 4) cam_from_world in the segment's world and units.
        scale, R (3, 3), t (3,): the similarity segment world -> current world.
    Returns:
        (M, 4, 4) cam_from_world in the current world and units (NaN rows stay NaN):
        rotation R_c R^T, translation scale t_c - R_c R^T t.
    """
    T = np.asarray(seg_cam_from_world, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"seg_cam_from_world must be (M, 4, 4), got {T.shape}")
    Rc, tc = T[:, :3, :3], T[:, :3, 3]
    R_new = Rc @ np.asarray(R, np.float64).T
    out = np.zeros_like(T)
    out[:, :3, :3] = R_new
    out[:, :3, 3] = float(scale) * tc - R_new @ np.asarray(t, np.float64)
    out[:, 3, 3] = 1.0
    out[~np.isfinite(T).all(axis=(1, 2))] = np.nan
    return out


def _anchor_points(cam_from_world: np.ndarray) -> tuple[np.ndarray, float]:
    """(A, 4, 4) -> ((4A, 3) points, L): camera centres and centre + L * each camera axis (rows of R).

    L is the median distance of the centres from their mean, which scales exactly with the
    world (so the axis points transform by the same similarity as the centres)."""
    c = camera_centers(torch.from_numpy(cam_from_world)).numpy()
    L = float(np.median(np.linalg.norm(c - c.mean(0), axis=1)))
    axes = cam_from_world[:, :3, :3]  # row k: camera axis k in world coordinates
    return np.concatenate([c, (c[:, None, :] + L * axes).reshape(-1, 3)]), L


def fit_segment_sim3(seg_anchor_poses: np.ndarray, cur_anchor_poses: np.ndarray):
    """Sim(3) (scale, R, t) with x_cur = scale R x_seg + t from anchor poses (A, 4, 4) in both worlds.

    Raises ValueError when the anchors' centres coincide (no scale)."""
    src, L_src = _anchor_points(seg_anchor_poses)
    dst, L_dst = _anchor_points(cur_anchor_poses)
    if not (L_src > 1e-12 and L_dst > 1e-12):
        raise ValueError("the anchor frames' camera centres coincide: no scale")
    return umeyama(src, dst, with_scale=True)


def pose_change(old: np.ndarray, new: np.ndarray) -> tuple[float, float]:
    """(rotation change in degrees, camera-centre displacement in world units) between two cam_from_world."""
    if not (np.isfinite(old).all() and np.isfinite(new).all()):
        return float("nan"), float("nan")
    dR = new[:3, :3] @ old[:3, :3].T
    ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
    c = camera_centers(torch.from_numpy(np.stack([old, new]))).numpy()
    return ang, float(np.linalg.norm(c[1] - c[0]))


# ------------------------------------------------------------------ records
def full_resolution(seq: Sequence) -> Sequence:
    """The record of the frame files' window at their native size (SfM downsizes it to ``sfm.max_size``)."""
    if seq.native_window is None:
        return seq
    from endorecon.data.transforms import resize_sequence

    _, _, w, h = seq.native_window
    return resize_sequence(seq, int(h), int(w))


def previous_iteration_dir(out_dir: Path) -> Path | None:
    """``<run>/iteration=<i-1>/sequences/<slug>`` for ``out_dir = <run>/iteration=<i>/sequences/<slug>``; None if the
    layout differs or i == 0."""
    out_dir = Path(out_dir)
    it_dir = out_dir.parent.parent
    if out_dir.parent.name != "sequences" or not it_dir.name.startswith("iteration="):
        return None
    try:
        i = int(it_dir.name.split("=", 1)[1])
    except ValueError:
        return None
    if i <= 0:
        return None
    return it_dir.parent / f"iteration={i - 1}" / "sequences" / out_dir.name


def earlier_reruns(out_dir: Path) -> list[dict]:
    """The ``resfm.json`` records of every earlier iteration of this sequence (oldest last)."""
    out, d = [], previous_iteration_dir(out_dir)
    while d is not None:
        p = d / "resfm.json"
        if p.is_file():
            try:
                out.append(json.loads(p.read_text()))
            except ValueError:
                log.warning("unreadable %s ignored", p)
        d = previous_iteration_dir(d)
    return out


def _count_earlier(rng: tuple[int, int], history: list[dict]) -> int:
    """How many earlier reruns covered a range overlapping ``rng``."""
    n = 0
    for rec in history:
        for r in rec.get("ranges", []):
            a, b = r["range"]
            if r.get("status") != "not_run" and a <= rng[1] and rng[0] <= b:
                n += 1
                break
    return n


# ------------------------------------------------------------------ the step
def rerun_repeated_failures(cfg: DictConfig, seq: Sequence, report, previous_report, poses: np.ndarray,
                            out_dir: Path, history: list[dict] | None = None) -> tuple[np.ndarray, dict]:
    """Rerun SfM on the ranges flagged in this and the previous iteration and splice the aligned poses in.

    Args:
        cfg: the full config (``failure.rerun``, ``sfm``).
        seq: the sequence (any resolution: SfM runs on the frame files' native window).
        report: this iteration's :class:`endorecon.failure.FailureReport` (needs ``n_frames`` or ``seq``).
        previous_report: the previous iteration's report, or None (no-op).
        poses: (N, 4, 4) current cam_from_world (NaN rows unregistered).
        out_dir: this sequence's iteration dir; reruns go to ``out_dir/resfm/``, the record to ``resfm.json``.
        history: earlier iterations' ``resfm.json`` records (attempt counting); default: none.
    Returns:
        (new poses (N, 4, 4), info dict).  A range that cannot be rerun or aligned keeps its poses and says why.
    """
    from endorecon.sfm.stage import DEFAULTS as SFM_DEFAULTS
    from endorecon.sfm.stage import SfMError, rerun

    out_dir = Path(out_dir)
    poses = np.asarray(poses, dtype=np.float64)
    n = len(poses)
    if poses.shape != (n, 4, 4) or n != len(seq):
        raise ValueError(f"poses must be ({len(seq)}, 4, 4), got {poses.shape}")
    rc = rerun_cfg(cfg)
    info: dict = dict(ranges=[], replaced_frames=[])
    if previous_report is None:
        info["skipped"] = "no previous failure report"
        return poses, info
    repeat = report.repeat_ranges(previous_report)
    if not repeat:
        info["skipped"] = "no range flagged in two consecutive iterations"
        return poses, info

    cfg_sfm = cfg.get("sfm")
    n_attempts = len((cfg_sfm.get("attempts") if cfg_sfm is not None else None) or SFM_DEFAULTS["attempts"])
    pad, min_anchor = int(rc["pad"]), int(rc["min_anchor_frames"])
    radius = rc["replace_radius"]
    if radius is None:  # the frames the loop excludes from fusion around a flagged frame
        radius = cfg.get("failure", {}).get("exclude_radius") if cfg is not None else None
    radius = report.interval // 2 if radius is None else int(radius)
    if radius < 0:  # checked before any SfM runs (it crashed after one)
        raise InputError(f"failure.rerun.replace_radius / failure.exclude_radius must be >= 0, got {radius}",
                         fix="use 0 <= radius < failure.rerun.pad (defaults: radius 2, pad 5)")
    if 2 * (pad - radius) < min_anchor:  # visible, not fatal: each range is then recorded as not aligned
        log.warning("failure.rerun: radius %d with pad %d leaves an inner range %d anchor frame(s) (< %d): its "
                    "SfM rerun cannot be aligned", radius, pad, max(0, 2 * (pad - radius)), min_anchor)
    bad = np.zeros(n, bool)
    bad[[f for f in report.excluded_frames(radius) if f < n]] = True
    bad[[f for f in report.flagged_frames if f < n]] = True
    full = full_resolution(seq)
    history = history or []
    new = poses.copy()
    for a, b in repeat:
        rec = dict(range=[int(a), int(b)])
        info["ranges"].append(rec)
        replace = np.arange(max(0, a - radius), min(n - 1, b + radius) + 1)
        first, last = max(0, a - pad), min(n - 1, b + pad)
        attempt = min(int(rc["first_attempt"]) + _count_earlier((a, b), history), n_attempts - 1)
        rec.update(segment=[int(first), int(last)], attempt=int(attempt), replace=[int(replace[0]), int(replace[-1])])
        if last - first < 2:
            rec.update(status="not_run", reason=f"segment {first}..{last} has fewer than 3 frames")
            log.warning("%s: SfM rerun of %s skipped: %s", seq.name, (a, b), rec["reason"])
            continue
        seg_dir = out_dir / "resfm" / f"{first:05d}_{last:05d}_attempt{attempt}"
        try:
            seg = rerun(cfg_sfm, full, (first, last), attempt, seg_dir)
        except InputError as e:  # SfMError included: no model at all, bad frames ...
            rec.update(status="sfm_failed", reason=str(e).splitlines()[0],
                       error_type="SfMError" if isinstance(e, SfMError) else type(e).__name__)
            log.warning("%s: SfM rerun of frames %d..%d (attempt %d) failed: %s", seq.name, first, last, attempt, e)
            continue
        seg_T = np.asarray(seg.cam_from_world, dtype=np.float64)
        if seg_T.shape != (last - first + 1, 4, 4):
            rec.update(status="not_aligned", reason=f"rerun returned {seg_T.shape[0]} poses for {last - first + 1} frames")
            continue
        seg_reg = np.isfinite(seg_T).all(axis=(1, 2))
        cur_reg = np.isfinite(poses).all(axis=(1, 2))
        idx = np.arange(first, last + 1)
        in_replace = (idx >= replace[0]) & (idx <= replace[-1])
        anchors = idx[~in_replace & ~bad[idx] & seg_reg & cur_reg[idx]]
        rec["anchors"] = [int(i) for i in anchors]
        rec["segment_registered"] = int(seg_reg.sum())
        if len(anchors) < min_anchor:
            rec.update(status="not_aligned",
                       reason=f"{len(anchors)} anchor frame(s) (unflagged pad frames registered in both) < "
                              f"min_anchor_frames={min_anchor}")
            log.warning("%s: SfM rerun of %s not used: %s", seq.name, (a, b), rec["reason"])
            continue
        try:
            s, R, t = fit_segment_sim3(seg_T[anchors - first], poses[anchors])
        except ValueError as e:
            rec.update(status="not_aligned", reason=str(e))
            log.warning("%s: SfM rerun of %s not used: %s", seq.name, (a, b), e)
            continue
        aligned = align_segment_poses(seg_T, s, R, t)
        c_cur = camera_centers(torch.from_numpy(poses[anchors])).numpy()
        c_new = camera_centers(torch.from_numpy(aligned[anchors - first])).numpy()
        rec.update(sim3=dict(scale=float(s), R=np.asarray(R).tolist(), t=np.asarray(t).tolist()),
                   anchor_rms=float(np.sqrt(((c_cur - c_new) ** 2).sum(1).mean())))
        changes, missing = {}, []
        for f in replace:
            if not seg_reg[f - first]:
                missing.append(int(f))
                continue
            rot, trans = pose_change(poses[f], aligned[f - first])
            new[f] = aligned[f - first]
            changes[str(int(f))] = dict(rotation_deg=rot, translation=trans)
            info["replaced_frames"].append(int(f))
        rec.update(status="replaced" if changes else "not_aligned", pose_change=changes, not_registered=missing)
        if not changes:
            rec["reason"] = "the rerun registered none of the frames to replace"
        log.info("%s: SfM rerun of frames %d..%d (attempt %d): %d pose(s) replaced, %d anchors, anchor rms %.3g",
                 seq.name, first, last, attempt, len(changes), len(anchors), rec["anchor_rms"])
    return new, info


def write_info(out_dir: Path, info: dict) -> Path:
    """``out_dir/resfm.json`` (atomically)."""
    return atomic_write_text(Path(out_dir) / "resfm.json", json.dumps(info, indent=2, default=float) + "\n")


def run(cfg: DictConfig, seq: Sequence, report, poses: np.ndarray, out_dir: Path) -> tuple[np.ndarray, dict]:
    """The loop's step: find the previous iteration's report from ``out_dir``'s layout
    (``<run>/iteration=<i>/sequences/<slug>``), rerun, write ``resfm.json``.  No-op (poses unchanged,
    ``info["skipped"]`` says why) when disabled, at iteration 0, or without a previous report."""
    from endorecon.failure import FailureReport

    out_dir = Path(out_dir)
    rc = rerun_cfg(cfg)
    prev_dir = previous_iteration_dir(out_dir)
    previous = None
    if not rc["enabled"]:
        info = dict(ranges=[], replaced_frames=[], skipped="failure.rerun.enabled is false")
    elif prev_dir is None or not (prev_dir / "failures.csv").is_file():
        info = dict(ranges=[], replaced_frames=[], skipped="no previous iteration's failures.csv")
    else:
        previous = FailureReport.read_csv(prev_dir / "failures.csv", interval=report.interval)
        previous.n_frames = len(seq)
        poses, info = rerun_repeated_failures(cfg, seq, report, previous, poses, out_dir,
                                              history=earlier_reruns(out_dir))
    if previous is not None:
        info["previous_report"] = str(prev_dir / "failures.csv")
    write_info(out_dir, info)
    return poses, info

"""Failure detection: flag frames whose depth or pose disagrees with the fused geometry or SfM.

Every ``interval``-th frame, and the last one (``check_last_frame``), is checked with the three metrics of the
method, all Gaussian NLLs from :mod:`endorecon.losses` (per frame, mean over pixels):

* ``dense_simulation``: the network's depth vs the simulated depth (the fused
  mesh rendered at the frame's pose).  Catches a bad depth prediction, and a
  bad pose (the mesh, built mostly from the other frames, seen from the wrong
  place no longer matches what the network sees).
* ``sparse_flow``: the flow implied by the network's depth and the SfM relative
  pose to a neighbour vs the sparse SfM tracks.  Catches a bad pose and a
  badly scaled/shaped depth.
* ``depth_consistency``: the neighbour's simulated depth warped into the frame
  with the relative pose vs the frame's own simulated depth
  (``depth_consistency_source: simulated``, the paper).  Renderings of one mesh
  agree under the relative pose *of the poses they were rendered at*, so this
  metric reacts when the pose being checked differs from the rendering pose
  (e.g. SfM poses checked against depths rendered at refined poses) and to mesh
  defects (holes, ghost layers).  ``network`` compares the frame's *network*
  depth with the neighbour's simulated depth instead, which also catches a
  frame rendered at its own wrong pose.

A metric exceeding its threshold flags the frame.  Over several neighbours the
per-pair values are reduced with ``neighbor_reduction`` (default ``min``: a
frame is blamed only when it disagrees with every neighbour, so a bad frame
does not also flag the good frames next to it).

**Hysteresis** (``low_thresholds``).  A failure is a stretch of video, not a
single frame, and its edge scores between a working frame and a failed one.
A checked frame next to a flagged checked frame is flagged as well when a
metric exceeds that metric's *low* threshold (reason ``low:<metric>``); this
repeats, so a run of frames over the low thresholds joins the flagged frame at
its end.  A frame with no flagged neighbour needs the full threshold.  A metric
without a low threshold has no hysteresis.  On the phantom's train-only patients
(the trainings of stops 43-45) no unflagged check away from a flagged one scored
over -0.32 on the dense simulation metric (3,054 checks), while the 24 next to
one scored up to 1.24 (README).

**Scale.**  For a Gaussian NLL, NLL(s·d, s·σ) = NLL(d, σ) + log s: the
thresholds (2.0 / 0.1 / 2.0, from the paper) only mean something at a fixed
depth scale.  With ``normalize_depth`` every depth, std and pose translation is
divided by the median network depth inside the mask first, so the metrics are
those of a sequence whose median depth is 1, as the SfM normalisation produces
(and then the normalisation is a no-op).  The flow metric is scale-free in the
flow itself (normalised by image size); only its std depends on the depth std.

Unregistered frames (NaN pose) are reported with NaN metrics and flagged with
reason ``unregistered``.  A metric without enough valid pixels is NaN and does
not flag.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import torch

from endorecon.geometry import relative_pose
from endorecon.geometry._checks import check_shape
from endorecon.losses import dense_simulation_loss, depth_consistency_loss, sparse_flow_loss
from endorecon.utils.errors import InputError, finite_number
from endorecon.utils.io import atomic_write_text

METRICS = ("dense_simulation", "sparse_flow", "depth_consistency")

DEFAULTS = {
    "interval": 5,
    "neighbor_offsets": [-5, 5],
    "neighbor_reduction": "min",
    "thresholds": {"dense_simulation": 2.0, "sparse_flow": 0.1, "depth_consistency": 2.0},
    "depth_consistency_source": "simulated",
    "normalize_depth": True,
    "min_valid_pixels": 20,
    "exclude_radius": 2,
    "batch_size": 16,
    "check_last_frame": True,
    "low_thresholds": None,  # no hysteresis (configs from before it existed)
}

LOW_PREFIX = "low:"  # reason of a frame flagged by the hysteresis: "low:dense_simulation"

SparseFlowFn = Callable[[int, int], "tuple[torch.Tensor, torch.Tensor] | None"]


def _get(cfg, key):
    if cfg is not None and key in cfg and cfg[key] is not None:
        return cfg[key]
    return DEFAULTS[key]


def check_low_thresholds(low, thresholds: Mapping | None = None) -> dict[str, float]:
    """``failure.low_thresholds`` checked: metric -> low threshold (metrics left out or null: no hysteresis).

    Each must be a finite number no higher than the metric's threshold (``thresholds``, default the defaults):
    above it, the "low" threshold would flag less next to a failure than elsewhere."""
    if low is None:
        return {}
    fix = ("pass e.g. failure.low_thresholds.dense_simulation=1.0, or failure.low_thresholds=null for no "
           "hysteresis")
    try:
        items = dict(low).items()
    except (TypeError, ValueError):
        raise InputError(f"failure.low_thresholds must be a mapping metric -> number (or null), got {low!r}",
                         fix=fix) from None
    thresholds = {**DEFAULTS["thresholds"], **dict(thresholds or {})}
    out = {}
    for m, v in items:
        if m not in METRICS:
            raise InputError(f"failure.low_thresholds.{m}: unknown metric (the metrics are {', '.join(METRICS)})",
                             fix=fix)
        if v is None:
            continue
        x = finite_number(v)
        if x is None or not x <= float(thresholds[m]):
            raise InputError(f"failure.low_thresholds.{m} must be a number no higher than failure.thresholds.{m} "
                             f"({thresholds[m]}), got {v!r}", fix=fix)
        out[m] = x
    return out


def _ranges(frames: list[int], min_gap: int, pad: int = 0, n_frames: int | None = None) -> list[tuple[int, int]]:
    """Merge sorted frame indices whose gap is <= min_gap into inclusive (first, last) ranges."""
    out: list[list[int]] = []
    for f in sorted(frames):
        if out and f - out[-1][1] <= min_gap:
            out[-1][1] = f
        else:
            out.append([f, f])
    hi = math.inf if n_frames is None else n_frames - 1
    return [(max(0, a - pad), int(min(hi, b + pad))) for a, b in out]


@dataclasses.dataclass
class FailureReport:
    """Per checked frame: the three metrics, which exceeded their threshold, and whether it is flagged.

    Attributes:
        frames: (M,) checked frame indices.
        metrics: name -> (M,) float values (NaN: not computable).
        exceeded: name -> (M,) bool.
        flagged: (M,) bool.
        reasons: M strings ("" | "dense_simulation+sparse_flow" | "unregistered" ...).
        interval: the check interval.
        n_frames: sequence length (None when read from a CSV).
        depth_scale: the depth normalisation applied (1.0 = none).
    """

    frames: np.ndarray
    metrics: dict[str, np.ndarray]
    exceeded: dict[str, np.ndarray]
    flagged: np.ndarray
    reasons: list[str]
    interval: int = 5
    n_frames: int | None = None
    depth_scale: float = 1.0

    @property
    def flagged_frames(self) -> list[int]:
        """Checked frames that are flagged (excluded from fusion by the loop)."""
        return [int(f) for f in self.frames[self.flagged]]

    def excluded_frames(self, radius: int | None = None) -> list[int]:
        """Flagged checked frames and the frames within ``radius`` of them (default ``interval // 2``).

        Only every ``interval``-th frame is checked; ``interval // 2`` assigns each
        unchecked frame to its nearest checked frame's verdict.
        """
        r = self.interval // 2 if radius is None else int(radius)
        hi = (self.n_frames - 1) if self.n_frames is not None else None
        out = set()
        for f in self.flagged_frames:
            for g in range(f - r, f + r + 1):
                if g >= 0 and (hi is None or g <= hi):
                    out.add(g)
        return sorted(out)

    def flagged_ranges(self, min_gap: int | None = None, pad: int = 0) -> list[tuple[int, int]]:
        """Flagged frames merged into inclusive (first, last) ranges.

        Flagged frames at most ``min_gap`` apart (default ``interval``: consecutive
        checked frames) share a range; each range is widened by ``pad`` frames.
        """
        gap = self.interval if min_gap is None else int(min_gap)
        return _ranges(self.flagged_frames, gap, pad, self.n_frames)

    def repeat_ranges(self, previous: "FailureReport", min_gap: int | None = None) -> list[tuple[int, int]]:
        """This report's flagged ranges that overlap a range flagged in ``previous`` (the last iteration).

        These segments failed twice: the loop reruns SfM on them
        (``sfm.rerun(segment, attempt)``).
        """
        prev = previous.flagged_ranges(min_gap)
        return [r for r in self.flagged_ranges(min_gap) if any(r[0] <= b and a <= r[1] for a, b in prev)]

    @property
    def low_flagged_frames(self) -> list[int]:
        """Checked frames flagged by the hysteresis only (next to a flagged frame, over a low threshold)."""
        return [int(f) for f, r in zip(self.frames, self.reasons) if r.startswith(LOW_PREFIX)]

    def summary(self) -> str:
        n = len(self.frames)
        parts = [f"{int(self.flagged.sum())}/{n} checked frames flagged (interval {self.interval})"]
        if self.low_flagged_frames:
            parts.append(f"{len(self.low_flagged_frames)} of them at a low threshold next to a flagged frame "
                         f"({', '.join(map(str, self.low_flagged_frames))})")
        for m in METRICS:
            v = self.metrics[m]
            fin = v[np.isfinite(v)]
            med = f"{np.median(fin):.3g}" if len(fin) else "nan"
            parts.append(f"{m}: {int(self.exceeded[m].sum())} over, median {med}")
        unreg = sum(r == "unregistered" for r in self.reasons)
        if unreg:
            parts.append(f"{unreg} unregistered")
        s = "; ".join(parts)
        if self.flagged.any():
            s += "; flagged frames " + ", ".join(map(str, self.flagged_frames))
        return s

    def scalars(self) -> dict[str, float]:
        """Counts and medians for TensorBoard (``failure/...``)."""
        out = {"failure/checked": float(len(self.frames)), "failure/flagged": float(self.flagged.sum())}
        for m in METRICS:
            v = self.metrics[m]
            fin = v[np.isfinite(v)]
            out[f"failure/{m}_over"] = float(self.exceeded[m].sum())
            out[f"failure/{m}_median"] = float(np.median(fin)) if len(fin) else float("nan")
        return out

    def to_csv(self, path: str | Path) -> Path:
        """Write atomically: columns frame, dense_simulation, sparse_flow, depth_consistency, flagged, reason."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["frame", *METRICS, "flagged", "reason"])
        for k, f in enumerate(self.frames):
            w.writerow([int(f), *(f"{self.metrics[m][k]:.6g}" for m in METRICS), int(self.flagged[k]), self.reasons[k]])
        return atomic_write_text(path, buf.getvalue())

    @classmethod
    def read_csv(cls, path: str | Path, interval: int = 5) -> "FailureReport":
        """Read a report written by :meth:`to_csv` (thresholds are not stored: ``exceeded`` comes from ``reason``)."""
        path = Path(path)
        if not path.is_file():
            raise InputError("failure report is missing", path, "run failure detection for that iteration first")
        try:
            rows = list(csv.DictReader(path.read_text().splitlines()))
            frames = np.array([int(r["frame"]) for r in rows], dtype=np.int64)
            metrics = {m: np.array([float(r[m]) for r in rows]) for m in METRICS}
            flagged = np.array([bool(int(r["flagged"])) for r in rows], dtype=bool)
            reasons = [r["reason"] for r in rows]
            if any(v is None for r in rows for v in r.values()):  # a short row: DictReader fills in None
                raise ValueError("a row has fewer columns than the header")
        except (KeyError, ValueError, TypeError) as e:
            raise InputError(f"not a failure report ({e})", path, "delete it and rerun failure detection") from e
        exceeded = {m: np.array([m in r.split("+") for r in reasons], dtype=bool) for m in METRICS}
        return cls(frames, metrics, exceeded, flagged, reasons, interval=interval)


def _median_depth(depth: torch.Tensor, mask: torch.Tensor, frames: list[int]) -> float:
    d = depth[frames][mask[None].expand(len(frames), -1, -1, -1)]
    d = d[torch.isfinite(d) & (d > 0)]
    if len(d) == 0:
        raise ValueError("no valid depth inside the mask")
    step = max(1, len(d) // 1_000_000)  # a subsample is enough for a median
    return float(d[::step].median())


def detect_failures(
    depth: torch.Tensor,
    std: torch.Tensor,
    sim_depth: torch.Tensor,
    sim_valid: torch.Tensor,
    K: torch.Tensor,
    cam_from_world: torch.Tensor,
    mask: torch.Tensor,
    sparse_flow_fn: SparseFlowFn,
    cfg: Mapping | None = None,
) -> FailureReport:
    """Check every ``interval``-th frame (and the last, ``check_last_frame``) with the three metrics and flag
    those over threshold.

    Args:
        depth: (N, 1, H, W) network depth.
        std: (N, 1, H, W) network std.
        sim_depth: (N, 1, H, W) simulated depth (fused mesh rendered at each frame's pose), 0 = none.
        sim_valid: (N, 1, H, W) bool.
        K: (3, 3) or (N, 3, 3) pixel-centre intrinsics.
        cam_from_world: (N, 4, 4); NaN rows = unregistered.
        mask: (1, H, W) bool valid-pixel mask.
        sparse_flow_fn: ``(i, j) -> (flow (2, H, W) pixels i->j at i's pixels, valid (1, H, W))`` or None.
        cfg: keys of ``conf/failure/default.yaml`` (missing keys take those defaults).
    Returns:
        :class:`FailureReport`.
    """
    N, _, H, W = check_shape(depth, "depth", (None, 1, None, None))
    check_shape(std, "std", (N, 1, H, W))
    check_shape(sim_depth, "sim_depth", (N, 1, H, W))
    check_shape(sim_valid, "sim_valid", (N, 1, H, W))
    check_shape(cam_from_world, "cam_from_world", (N, 4, 4))
    check_shape(mask, "mask", (1, H, W))
    if K.shape == (3, 3):
        K = K.expand(N, 3, 3)
    check_shape(K, "K", (N, 3, 3))
    interval = int(_get(cfg, "interval"))
    if interval < 1:
        raise ValueError(f"failure.interval must be >= 1, got {interval}")
    offsets = [int(o) for o in _get(cfg, "neighbor_offsets")]
    thresholds = {**DEFAULTS["thresholds"], **dict(_get(cfg, "thresholds"))}
    source = str(_get(cfg, "depth_consistency_source"))
    if source not in ("simulated", "network"):
        raise ValueError(f"failure.depth_consistency_source must be 'simulated' or 'network', got {source!r}")
    reduce_name = str(_get(cfg, "neighbor_reduction"))
    reducers = {"min": np.nanmin, "mean": np.nanmean, "max": np.nanmax}
    if reduce_name not in reducers:
        raise ValueError(f"failure.neighbor_reduction must be one of {sorted(reducers)}, got {reduce_name!r}")
    min_valid = int(_get(cfg, "min_valid_pixels"))
    batch = max(1, int(_get(cfg, "batch_size")))
    low = check_low_thresholds(_get(cfg, "low_thresholds"), thresholds)

    dt = depth.dtype
    registered = torch.isfinite(cam_from_world.flatten(1)).all(1)
    checked = list(range(0, N, interval))
    # the last frame too: the frames after the last multiple of interval were judged by nobody (with 60 frames,
    # 58 and 59 lay beyond frame 55's exclusion radius), and the end of a video often looks farthest
    if _get(cfg, "check_last_frame") and checked[-1] != N - 1:
        checked.append(N - 1)
    reg_frames = [i for i in range(N) if registered[i]]
    scale = 1.0
    if _get(cfg, "normalize_depth") and reg_frames:
        scale = _median_depth(depth.detach(), mask, reg_frames)
    with torch.no_grad():
        depth_n, std_n, sim_n = depth / scale, std / scale, sim_depth / scale
        T = cam_from_world.to(dt).clone()
        T[:, :3, 3] /= scale
        mask_b = mask.bool()

        metrics = {m: np.full(len(checked), np.nan) for m in METRICS}
        pos = {f: k for k, f in enumerate(checked)}
        # Dense simulation: one value per checked frame, batched.
        idx = [i for i in checked if registered[i]]
        for s in range(0, len(idx), batch):
            b = idx[s : s + batch]
            valid = sim_valid[b].bool() & mask_b[None] & (sim_n[b] > 0)
            vals = dense_simulation_loss(depth_n[b], std_n[b], sim_n[b], valid, reduction="none", min_valid=min_valid)
            for f, v in zip(b, vals.tolist()):  # NaN: fewer than min_valid pixels
                metrics["dense_simulation"][pos[f]] = v

        # Pairs (checked frame, neighbour) for sparse flow and depth consistency.
        pairs = [(i, i + o) for i in idx for o in offsets if 0 <= i + o < N and registered[i + o] and o != 0]
        per_pair = {m: {} for m in ("sparse_flow", "depth_consistency")}
        for s in range(0, len(pairs), batch):
            chunk = pairs[s : s + batch]
            ii = [p[0] for p in chunk]
            jj = [p[1] for p in chunk]
            T_ji = relative_pose(T[ii], T[jj])
            Kc = K[ii].to(dt)
            # Depth consistency on simulated depth (or network depth of i vs simulated depth of j).
            if source == "simulated":
                d_i, m_i = sim_n[ii], mask_b[None] & sim_valid[ii].bool()
            else:
                d_i, m_i = depth_n[ii], mask_b[None].expand(len(ii), -1, -1, -1)
            # NaN for a pair with too little overlap: the loss counts the pixels it used, which m_i does not
            # (the warp leaves out what falls outside j or on j's holes), and 0 is no neutral NLL value.
            vals = depth_consistency_loss(
                d_i, std_n[ii], sim_n[jj], std_n[jj], Kc, T_ji, m_i, reduction="none",
                mask_j=mask_b[None].expand(len(jj), -1, -1, -1), min_valid=min_valid,
            )
            for p, v in zip(chunk, vals.tolist()):
                per_pair["depth_consistency"][p] = v if math.isfinite(v) else np.nan
            # Sparse flow, only for pairs that have tracks.
            flows, fvalid, keep = [], [], []
            for k, (i, j) in enumerate(chunk):
                got = sparse_flow_fn(i, j)
                if got is None:
                    continue
                f, v = got
                check_shape(f, "sparse flow", (2, H, W))
                check_shape(v, "sparse flow valid", (1, H, W))
                v = v.bool() & mask_b
                if int(v.sum()) < min_valid:
                    continue
                flows.append(f.to(dt))
                fvalid.append(v)
                keep.append(k)
            if keep:
                vals = sparse_flow_loss(
                    depth_n[[ii[k] for k in keep]], std_n[[ii[k] for k in keep]], Kc[keep], T_ji[keep],
                    torch.stack(flows), torch.stack(fvalid), reduction="none", min_valid=min_valid,
                )
                for k, v in zip(keep, vals.tolist()):
                    per_pair["sparse_flow"][chunk[k]] = v

    for m, d in per_pair.items():
        for k, f in enumerate(checked):
            vals = [d[p] for p in d if p[0] == f and np.isfinite(d[p])]
            if vals:
                metrics[m][k] = float(reducers[reduce_name](np.array(vals)))

    exceeded = {m: np.nan_to_num(metrics[m], nan=-np.inf) > float(thresholds[m]) for m in METRICS}
    flagged = np.zeros(len(checked), dtype=bool)
    reasons = []
    for k, f in enumerate(checked):
        if not registered[f]:
            flagged[k] = True
            reasons.append("unregistered")
            continue
        over = [m for m in METRICS if exceeded[m][k]]
        flagged[k] = bool(over)
        reasons.append("+".join(over))
    _hysteresis(metrics, low, flagged, reasons)
    return FailureReport(
        frames=np.array(checked, dtype=np.int64), metrics=metrics, exceeded=exceeded, flagged=flagged,
        reasons=reasons, interval=interval, n_frames=N, depth_scale=scale,
    )


def _hysteresis(metrics: dict[str, np.ndarray], low: dict[str, float], flagged: np.ndarray,
                reasons: list[str]) -> None:
    """Flag (in place) every checked frame next to a flagged one with a metric over its low threshold, until
    none is left: a run of such frames joins the flagged frame at its end."""
    over_low = {m: np.nan_to_num(metrics[m], nan=-np.inf) > t for m, t in low.items()}
    grew = bool(low)
    while grew:
        grew = False
        for k in range(len(flagged)):
            if flagged[k] or not ((k > 0 and flagged[k - 1]) or (k + 1 < len(flagged) and flagged[k + 1])):
                continue
            over = [m for m in METRICS if m in over_low and over_low[m][k]]
            if over:
                flagged[k] = grew = True
                reasons[k] = "+".join(LOW_PREFIX + m for m in over)


def run(
    cfg: Mapping | None,
    depth: torch.Tensor,
    std: torch.Tensor,
    sim_depth: torch.Tensor,
    sim_valid: torch.Tensor,
    K: torch.Tensor,
    cam_from_world: torch.Tensor,
    mask: torch.Tensor,
    sparse_flow_fn: SparseFlowFn,
    out_dir: str | Path,
) -> Path:
    """Stage entry: write ``<out_dir>/failures.csv`` (skipped when it exists) and return its path."""
    path = Path(out_dir) / "failures.csv"
    if path.is_file():
        return path
    report = detect_failures(depth, std, sim_depth, sim_valid, K, cam_from_world, mask, sparse_flow_fn, cfg)
    return report.to_csv(path)

"""Depth accuracy against ground-truth depth (phantom sequences): the SCARED / KITTI metric set.

Per frame: keep pixels that are valid with finite gt > 0 (and gt <= cap when a
cap is given), optionally rescale the prediction by median(gt) / median(pred)
(monocular depth is up to scale; medians over the pixels whose prediction is
finite and > 0), clamp it to the cap, compute the metrics, then average over
frames (as monodepth2 / SCARED).  A prediction that is not finite or not > 0 is
scored as the floor ``INVALID_PRED_FLOOR`` x the frame's median gt, never left
out (a network that fails on its hard pixels must not score better for it), and
counted in ``n_invalid_pred``.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import spearmanr

METRIC_NAMES = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
# Bins of GT depth over the frame's median GT depth for :func:`depth_error_by_range`: the near walls
# (often saturated by the light) and the far end of a passage (dark, few SfM points) are where
# held-out depth goes wrong, and a frame-averaged AbsRel hides which end it is.
RELATIVE_DEPTH_EDGES = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, float("inf"))
INVALID_PRED_FLOOR = 1e-3


def _as_frames(x, name: str) -> torch.Tensor:
    """(N, H, W) or (B, 1, H, W), numpy or torch -> (N, H, W) float64 tensor (bool kept bool)."""
    t = torch.as_tensor(np.asarray(x)) if not isinstance(x, torch.Tensor) else x
    t = t.detach().cpu()
    if t.dim() == 4:
        if t.shape[1] != 1:
            raise ValueError(f"{name} must be (N, H, W) or (B, 1, H, W), got {tuple(t.shape)}")
        t = t[:, 0]
    elif t.dim() == 2:
        t = t[None]
    if t.dim() != 3:
        raise ValueError(f"{name} must be (N, H, W) or (B, 1, H, W), got {tuple(t.shape)}")
    return t if t.dtype == torch.bool else t.to(torch.float64)


def _usable(pred, gt, valid):
    """(N, H, W) float64 pred and gt, and the bool mask of pixels with ground truth (valid, gt finite and > 0)."""
    p = _as_frames(pred, "pred")
    g = _as_frames(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred {tuple(p.shape)} and gt {tuple(g.shape)} differ in shape")
    m = torch.ones_like(g, dtype=torch.bool) if valid is None else _as_frames(valid, "valid")
    if m.shape != g.shape:
        raise ValueError(f"valid {tuple(m.shape)} and gt {tuple(g.shape)} differ in shape")
    return p, g, m.bool() & (g > 0) & torch.isfinite(g)


def _median(x: torch.Tensor) -> torch.Tensor:
    return torch.quantile(x, 0.5)  # the mean of the two middle values (torch.median takes the lower one)


def _scaled_frames(p, g, m, median_scaling: bool):
    """Per frame with ground truth: (scaled pred, gt, scale, number of invalid predictions) over its pixels;
    scale = median(gt)/median(pred) over the valid predictions, invalid ones set to the floor."""
    for pi, gi, mi in zip(p, g, m):
        if not mi.any():
            continue
        pv, gv = pi[mi], gi[mi]
        ok = torch.isfinite(pv) & (pv > 0)
        s = float(_median(gv[ok]) / _median(pv[ok])) if median_scaling and ok.any() else 1.0
        floor = INVALID_PRED_FLOOR * float(_median(gv))
        yield torch.where(ok, pv * s, torch.full_like(pv, floor)), gv, s, int((~ok).sum())


def depth_metrics(pred, gt, valid=None, median_scaling: bool = True, cap: float | None = None) -> dict:
    """SCARED/KITTI depth metrics averaged over frames.

    Args:
        pred: predicted depth, (N, H, W) or (B, 1, H, W) (also (H, W)), numpy or torch.
        gt: ground-truth depth, same shape; 0 = no ground truth.
        valid: optional bool mask, same shape (e.g. the endoscope's field of view).
        median_scaling: rescale each frame's prediction by median(gt)/median(pred) over its valid pixels.
        cap: maximum depth; pixels with gt > cap are ignored and predictions are clamped to it.
    Returns:
        {abs_rel, sq_rel, rmse, rmse_log, a1, a2, a3 (δ < 1.25, 1.25², 1.25³),
         scale_median (median of the per-frame scale factors; 1 without scaling),
         n_frames (frames with valid pixels), n_pixels, n_invalid_pred (pixels whose prediction was not
         finite or not > 0, scored at the floor)}.
    Raises:
        ValueError: wrong shapes or no valid pixel at all.
    """
    p, g, m = _usable(pred, gt, valid)
    if cap is not None:
        m &= g <= cap
    per_frame, scales, n_pix, n_bad = [], [], 0, 0
    for pv, gv, s, bad in _scaled_frames(p, g, m, median_scaling):
        n_bad += bad
        if cap is not None:
            pv = pv.clamp(max=cap)
        ratio = torch.maximum(gv / pv, pv / gv)
        per_frame.append(
            [
                ((gv - pv).abs() / gv).mean(),
                ((gv - pv) ** 2 / gv).mean(),
                ((gv - pv) ** 2).mean().sqrt(),
                ((gv.log() - pv.log()) ** 2).mean().sqrt(),
                (ratio < 1.25).double().mean(),
                (ratio < 1.25**2).double().mean(),
                (ratio < 1.25**3).double().mean(),
            ]
        )
        scales.append(s)
        n_pix += len(gv)
    if not per_frame:
        raise ValueError("no valid pixel (gt > 0, inside the mask and the cap) in any frame")
    mean = torch.tensor(per_frame, dtype=torch.float64).mean(0)
    out = {k: float(v) for k, v in zip(METRIC_NAMES, mean)}
    out.update(scale_median=float(np.median(scales)), n_frames=len(per_frame), n_pixels=n_pix, n_invalid_pred=n_bad)
    return out


def depth_error_by_range(pred, gt, valid=None, edges=RELATIVE_DEPTH_EDGES, median_scaling: bool = True) -> list[dict]:
    """Depth error by relative depth: which part of the depth range a prediction gets wrong, and which way.

    Each frame's prediction is scaled by median(gt)/median(pred) over its valid pixels (as in
    :func:`depth_metrics`); each valid pixel is binned by r = gt / median(gt of its frame).  Statistics are
    over all pixels of a bin (pixel-weighted across frames, unlike :func:`depth_metrics`'s frame average).

    Args:
        pred, gt, valid: as in :func:`depth_metrics`.
        edges: increasing bin edges of r (the last may be inf); a bin is [lo, hi).
    Returns:
        one dict per bin: {lo, hi (None for inf, so that the JSON stays standard), share (fraction of all valid pixels), n_pixels, log_error (mean signed
        log(pred / gt): > 0 too far, < 0 too near), abs_rel}; log_error and abs_rel are None for an empty bin.
    Raises:
        ValueError: wrong shapes, edges not increasing, or no valid pixel at all.
    """
    edges = [float(e) for e in edges]
    if len(edges) < 2 or any(b <= a for a, b in zip(edges[:-1], edges[1:])):
        raise ValueError(f"edges must be increasing with at least two values, got {edges}")
    p, g, m = _usable(pred, gt, valid)
    rel, err = [], []
    for pv, gv, _, _ in _scaled_frames(p, g, m, median_scaling):
        rel.append(gv / _median(gv))
        err.append(torch.log(pv / gv))
    if not rel:
        raise ValueError("no valid pixel (gt > 0, inside the mask) in any frame")
    r, e = torch.cat(rel), torch.cat(err)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        k = (r >= lo) & (r < hi)
        n = int(k.sum())
        out.append(dict(lo=lo, hi=None if hi == float("inf") else hi, share=n / len(r), n_pixels=n,
                        log_error=float(e[k].mean()) if n else None,
                        abs_rel=float((e[k].exp() - 1).abs().mean()) if n else None))
    return out


def range_label(b: dict) -> str:
    """A bin of :func:`depth_error_by_range` as text: ``<0.5x``, ``1-1.5x``, ``>3x``."""
    lo, hi = b["lo"], b["hi"]
    return f"<{hi:g}x" if lo == 0 and hi is not None else (f">{lo:g}x" if hi is None else f"{lo:g}-{hi:g}x")


def format_depth_ranges(bins: list[dict]) -> str:
    """One line for a log: ``<0.5x +0.02 (20%) | 0.5-1x ...``, the signed mean log error per bin."""
    parts = []
    for b in bins:
        val = "n/a" if b["log_error"] is None else f"{b['log_error']:+.2f}"
        parts.append(f"{range_label(b)} {val} ({100 * b['share']:.0f}%)")
    return " | ".join(parts)


def std_error_spearman(std, abs_error, valid=None, max_samples: int = 200_000, seed: int = 0) -> float:
    """Spearman rank correlation between predicted std and actual absolute error over valid pixels.

    Args:
        std, abs_error: same shape, e.g. (B, 1, H, W) or (N, H, W), numpy or torch.
        valid: optional bool mask of that shape.
        max_samples: a random subset of this many pixels is used when there are more.
    Returns:
        ρ in [-1, 1]; NaN when either input is constant over the valid pixels.
    """
    s = torch.as_tensor(np.asarray(std) if not isinstance(std, torch.Tensor) else std.detach().cpu())
    e = torch.as_tensor(np.asarray(abs_error) if not isinstance(abs_error, torch.Tensor) else abs_error.detach().cpu())
    if s.shape != e.shape:
        raise ValueError(f"std {tuple(s.shape)} and abs_error {tuple(e.shape)} differ in shape")
    m = torch.isfinite(s) & torch.isfinite(e)
    if valid is not None:
        v = torch.as_tensor(np.asarray(valid) if not isinstance(valid, torch.Tensor) else valid.detach().cpu())
        if v.shape != s.shape:
            raise ValueError(f"valid {tuple(v.shape)} and std {tuple(s.shape)} differ in shape")
        m &= v.bool()
    sv = s[m].double().numpy()
    ev = e[m].double().numpy()
    if len(sv) < 3:
        raise ValueError(f"need at least 3 valid pixels, got {len(sv)}")
    if len(sv) > max_samples:
        idx = np.random.default_rng(seed).choice(len(sv), max_samples, replace=False)
        sv, ev = sv[idx], ev[idx]
    if np.ptp(sv) == 0 or np.ptp(ev) == 0:
        return float("nan")
    return float(spearmanr(sv, ev).statistic)

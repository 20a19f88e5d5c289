"""Depth accuracy against ground-truth depth (phantom sequences): the SCARED / KITTI metric set.

Per frame: keep pixels that are valid with gt > 0 and pred > 0 (and gt <= cap
when a cap is given), optionally rescale the prediction by
median(gt) / median(pred) (monocular depth is up to scale), clamp it to the
cap, compute the metrics, then average over frames (as monodepth2 / SCARED).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import spearmanr

METRIC_NAMES = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


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
         n_frames (frames with valid pixels), n_pixels}.
    Raises:
        ValueError: wrong shapes or no valid pixel at all.
    """
    p = _as_frames(pred, "pred")
    g = _as_frames(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred {tuple(p.shape)} and gt {tuple(g.shape)} differ in shape")
    m = torch.ones_like(g, dtype=torch.bool) if valid is None else _as_frames(valid, "valid")
    if m.shape != g.shape:
        raise ValueError(f"valid {tuple(m.shape)} and gt {tuple(g.shape)} differ in shape")
    m = m.bool() & (g > 0) & (p > 0) & torch.isfinite(g) & torch.isfinite(p)
    if cap is not None:
        m &= g <= cap
    per_frame, scales, n_pix = [], [], 0
    for pi, gi, mi in zip(p, g, m):
        if not mi.any():
            continue
        pv, gv = pi[mi], gi[mi]
        s = float(gv.median() / pv.median()) if median_scaling else 1.0
        pv = pv * s
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
        n_pix += int(mi.sum())
    if not per_frame:
        raise ValueError("no valid pixel (gt > 0, pred > 0, inside the mask and the cap) in any frame")
    mean = torch.tensor(per_frame, dtype=torch.float64).mean(0)
    out = {k: float(v) for k, v in zip(METRIC_NAMES, mean)}
    out.update(scale_median=float(np.median(scales)), n_frames=len(per_frame), n_pixels=n_pix)
    return out


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

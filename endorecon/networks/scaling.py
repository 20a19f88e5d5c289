"""Depth Scaling Layer: bring a network's up-to-scale depth to the SfM scale of its frame.

Per frame b, over the valid sparse points P_b, one of two estimators (``mode``):

* ``"ratio_of_sums"``: scale_b = Σ_{p∈P_b} sparse(p) / Σ_{p∈P_b} depth(p), a ratio of
  means.  It weights points by their depth, so the few far points of a frame decide
  much of its scale.
* ``"log_mean"``: scale_b = exp(mean_{p∈P_b} (log sparse(p) − log depth(p))), the
  geometric mean of the per-point ratios: every point counts the same whatever its
  depth, and a prediction near zero cannot blow it up (it enters as a logarithm).
  Points whose prediction is not above ``eps`` are left out.

Depth and std are both multiplied by scale_b, so the std stays relative to the
depth.  The scale is differentiable w.r.t. the prediction, as in the paper (the
network learns the shape; the scale is not a free output).  Frames without a
valid sparse point keep scale 1 and are reported in ``has_sparse`` (their loss
terms then have nothing to be compared with in SfM units).

Local scaling (inference only, :func:`scale_depth_locally`; a departure from the paper,
whose layer has one scale per frame): after the frame scale, the log ratio
res_p = log sparse(p) − log depth(p) of each valid sparse point p is spread over the
image with a Gaussian g(x) = exp(−|x|²/(2σ²)) (peak 1, cut at 3σ) into a field

    field(x) = Σ_p g(x − p) res_p / (Σ_p g(x − p) + prior),

and depth and std are multiplied by exp(field).  Near points the frame's own SfM
depth corrects the network's shape (on the phantom, far walls that the network
predicts too near, README); far from every point field → 0, i.e. the frame scale
holds; ``prior`` is how many points' worth of weight that pull towards 0 has.

With ``max_log_ratio`` set, a point whose res_p lies farther than that from the median res of its
frame is left out of the field: SfM keeps a few gross outliers (on the phantom, observations at a
fiftieth of the true depth, log error −5), and one of them alone would pull the depth around it
towards zero, where the network's own error is a few tenths in log at most.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from endorecon.geometry._checks import check_shape


SCALE_MODES = ("ratio_of_sums", "log_mean")


def check_scale_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`SCALE_MODES`, else a ValueError naming the config key."""
    if mode not in SCALE_MODES:
        raise ValueError(f"model.depth_scaling must be one of {SCALE_MODES}, got {mode!r}")
    return mode


def _log_ratio(depth: torch.Tensor, sparse_depth: torch.Tensor, valid: torch.Tensor, eps: float):
    """log sparse − log depth at ``valid`` points whose prediction is finite and above ``eps``, 0 elsewhere
    (log 1 − log 1, so no NaN/inf reaches a sum or a gradient).  -> (log_ratio, valid), each (B,1,H,W)."""
    valid = valid & torch.isfinite(depth) & (depth > eps)
    one = torch.ones((), dtype=depth.dtype, device=depth.device)
    return torch.log(torch.where(valid, sparse_depth, one)) - torch.log(torch.where(valid, depth, one)), valid


def depth_scale(
    depth: torch.Tensor,
    sparse_depth: torch.Tensor,
    sparse_valid: torch.Tensor,
    eps: float = 1e-8,
    mode: str = "ratio_of_sums",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame scale over valid sparse points (``mode``: see the module docstring).

    Args:
        depth: (B, 1, H, W) predicted depth (> 0).
        sparse_depth: (B, 1, H, W) SfM depth (ignored where not valid; may hold NaN there).
        sparse_valid: (B, 1, H, W) bool.
    Returns:
        scale: (B,) (1 where a frame has no valid point).
        has_sparse: (B,) bool.
    """
    B, _, H, W = check_shape(depth, "depth", (None, 1, None, None))
    check_shape(sparse_depth, "sparse_depth", (B, 1, H, W))
    check_shape(sparse_valid, "sparse_valid", (B, 1, H, W))
    check_scale_mode(mode)
    # a non-finite prediction at a point leaves that point out (with ratio_of_sums one NaN reset the whole frame)
    valid = sparse_valid.bool() & torch.isfinite(sparse_depth) & (sparse_depth > 0) & torch.isfinite(depth)
    if mode == "log_mean":
        log_ratio, valid = _log_ratio(depth, sparse_depth, valid, eps)
        n = valid.flatten(1).sum(1)
        has = n > 0
        scale = torch.exp(log_ratio.flatten(1).sum(1) / n.clamp(min=1).to(depth.dtype))  # 1 where n == 0
        return scale, has
    zero = torch.zeros((), dtype=depth.dtype, device=depth.device)
    num = torch.where(valid, sparse_depth, zero).flatten(1).sum(1)
    den = torch.where(valid, depth, zero).flatten(1).sum(1)
    has = valid.flatten(1).any(1) & (den > eps)
    scale = torch.where(has, num / torch.where(has, den, torch.ones_like(den)), torch.ones_like(den))
    return scale, has


def scale_depth(
    depth: torch.Tensor,
    std: torch.Tensor,
    sparse_depth: torch.Tensor,
    sparse_valid: torch.Tensor,
    eps: float = 1e-8,
    mode: str = "ratio_of_sums",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Apply the Depth Scaling Layer.

    Args:
        depth, std: (B, 1, H, W) network outputs.
        sparse_depth: (B, 1, H, W); sparse_valid: (B, 1, H, W) bool.
    Returns:
        depth_scaled, std_scaled: (B, 1, H, W).
        scale: (B,).  has_sparse: (B,) bool.
    """
    check_shape(std, "std", tuple(depth.shape))
    scale, has = depth_scale(depth, sparse_depth, sparse_valid, eps, mode)
    s = scale.view(-1, 1, 1, 1)
    return _times_scale(depth, s), _times_scale(std, s), scale, has


def _times_scale(x: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """x * s, with the non-finite entries of x passed through unscaled (same values for s > 0): d(x s)/ds sums x
    over every pixel, and one inf the losses leave out made s's gradient, so the whole batch's, NaN (0 * inf)."""
    finite = torch.isfinite(x)
    return torch.where(finite, torch.where(finite, x, torch.ones_like(x)) * s, x)


def _gaussian_sum(x: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Σ over pixels q of x(q) exp(−|p − q|²/(2σ²)), zero outside the image, cut at 3σ.  x: (B,1,H,W)."""
    r = max(1, math.ceil(3.0 * sigma_px))
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    g = torch.exp(-(t**2) / (2.0 * sigma_px**2))
    x = F.conv2d(x, g.view(1, 1, 1, -1), padding=(0, r))  # separable: rows, then columns
    return F.conv2d(x, g.view(1, 1, -1, 1), padding=(r, 0))


def local_log_scale(
    depth: torch.Tensor,
    sparse_depth: torch.Tensor,
    sparse_valid: torch.Tensor,
    sigma_px: float,
    prior: float,
    eps: float = 1e-8,
    max_log_ratio: float | None = None,
) -> torch.Tensor:
    """The log-scale field of the local scaling (module docstring).

    Args:
        depth: (B, 1, H, W) depth, already at the frame scale (> 0).
        sparse_depth: (B, 1, H, W) SfM depth (ignored where not valid; may hold NaN there).
        sparse_valid: (B, 1, H, W) bool.
        sigma_px: Gaussian σ in pixels (> 0).  prior: weight of field 0 (> 0).
        max_log_ratio: None (every valid point counts) or > 0: points whose log ratio is farther than
            this from their frame's median log ratio (the lower middle one when their number is even) are
            left out (outliers).
    Returns:
        field: (B, 1, H, W); 0 on frames without a valid point.
    """
    B, _, H, W = check_shape(depth, "depth", (None, 1, None, None))
    check_shape(sparse_depth, "sparse_depth", (B, 1, H, W))
    check_shape(sparse_valid, "sparse_valid", (B, 1, H, W))
    if not sigma_px > 0 or not prior > 0:
        raise ValueError(f"local scaling needs sigma_px > 0 and prior > 0, got {sigma_px}, {prior} "
                         "(model.local_scaling.sigma_fraction / prior)")
    if max_log_ratio is not None and not max_log_ratio > 0:
        raise ValueError(f"local scaling needs max_log_ratio > 0 or None, got {max_log_ratio} "
                         "(model.local_scaling.max_log_ratio)")
    valid = sparse_valid.bool() & torch.isfinite(sparse_depth) & (sparse_depth > 0)
    res, valid = _log_ratio(depth, sparse_depth, valid, eps)
    if max_log_ratio is not None:
        nan = torch.full_like(res, float("nan"))
        centre = torch.where(valid, res, nan).flatten(1).nanmedian(1).values.view(B, 1, 1, 1)  # NaN: no point
        valid = valid & ((res - centre).abs() <= max_log_ratio)
        res = torch.where(valid, res, torch.zeros_like(res))
    return _gaussian_sum(res, sigma_px) / (_gaussian_sum(valid.to(depth.dtype), sigma_px) + prior)


def scale_depth_locally(
    depth: torch.Tensor,
    std: torch.Tensor,
    sparse_depth: torch.Tensor,
    sparse_valid: torch.Tensor,
    sigma_px: float,
    prior: float,
    eps: float = 1e-8,
    max_log_ratio: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Local scaling of frame-scaled depth and std by their frame's sparse points (module docstring).

    Args:
        depth, std: (B, 1, H, W), e.g. the output of :func:`scale_depth`.
        sparse_depth: (B, 1, H, W); sparse_valid: (B, 1, H, W) bool.
        sigma_px, prior, max_log_ratio: see :func:`local_log_scale`.
    Returns:
        depth_scaled, std_scaled: (B, 1, H, W).  field: (B, 1, H, W) the log scale applied.
    """
    check_shape(std, "std", tuple(depth.shape))
    field = local_log_scale(depth, sparse_depth, sparse_valid, sigma_px, prior, eps, max_log_ratio)
    f = torch.exp(field)
    return depth * f, std * f, field


class DepthScalingLayer(nn.Module):
    """Module wrapper of :func:`scale_depth` (no parameters)."""

    def __init__(self, eps: float = 1e-8, mode: str = "ratio_of_sums"):
        super().__init__()
        self.eps, self.mode = eps, mode

    def forward(self, depth, std, sparse_depth, sparse_valid):
        return scale_depth(depth, std, sparse_depth, sparse_valid, self.eps, self.mode)

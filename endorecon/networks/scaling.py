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
"""

from __future__ import annotations

import torch
import torch.nn as nn

from endorecon.geometry._checks import check_shape


SCALE_MODES = ("ratio_of_sums", "log_mean")


def check_scale_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`SCALE_MODES`, else a ValueError naming the config key."""
    if mode not in SCALE_MODES:
        raise ValueError(f"model.depth_scaling must be one of {SCALE_MODES}, got {mode!r}")
    return mode


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
    valid = sparse_valid.bool() & torch.isfinite(sparse_depth) & (sparse_depth > 0)
    if mode == "log_mean":
        valid = valid & torch.isfinite(depth) & (depth > eps)
        one = torch.ones((), dtype=depth.dtype, device=depth.device)
        log_ratio = torch.log(torch.where(valid, sparse_depth, one)) - torch.log(torch.where(valid, depth, one))
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
    return depth * s, std * s, scale, has


class DepthScalingLayer(nn.Module):
    """Module wrapper of :func:`scale_depth` (no parameters)."""

    def __init__(self, eps: float = 1e-8, mode: str = "ratio_of_sums"):
        super().__init__()
        self.eps, self.mode = eps, mode

    def forward(self, depth, std, sparse_depth, sparse_valid):
        return scale_depth(depth, std, sparse_depth, sparse_valid, self.eps, self.mode)

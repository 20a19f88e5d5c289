"""Images for TensorBoard: colour-mapped depth, std, sparse points, warped-pair error."""

from __future__ import annotations

import torch
from matplotlib import colormaps


def colorize(x: torch.Tensor, mask: torch.Tensor | None = None, cmap: str = "viridis") -> torch.Tensor:
    """Colour-map a (1, H, W) map, normalised to its 2nd-98th percentile inside ``mask``; (3, H, W) in [0, 1]."""
    x = x.detach().float().cpu()[0]
    m = torch.isfinite(x) if mask is None else mask.cpu()[0].bool() & torch.isfinite(x)
    if m.any():
        vals = x[m]
        lo, hi = torch.quantile(vals, 0.02), torch.quantile(vals, 0.98)
        x = ((x - lo) / (hi - lo).clamp(min=1e-12)).clamp(0, 1)
    else:
        x = torch.zeros_like(x)
    rgb = torch.from_numpy(colormaps[cmap](torch.nan_to_num(x).numpy())[..., :3]).permute(2, 0, 1).float()
    return rgb * m.float() if mask is not None else rgb


def overlay_points(image: torch.Tensor, valid: torch.Tensor, color=(1.0, 0.0, 0.0)) -> torch.Tensor:
    """Paint the pixels where ``valid`` (1, H, W) is set on ``image`` (3, H, W), 3x3 dots."""
    img = image.detach().float().cpu().clone()
    v = valid.detach().cpu().float()[None]
    v = torch.nn.functional.max_pool2d(v, 3, stride=1, padding=1)[0, 0] > 0
    for c in range(3):
        img[c][v] = color[c]
    return img


def pair_panel(
    image: torch.Tensor,
    mask: torch.Tensor,
    depth: torch.Tensor,
    std: torch.Tensor,
    sparse_valid: torch.Tensor,
    rel_error: torch.Tensor,
    error_valid: torch.Tensor,
) -> torch.Tensor:
    """One row: input | mean depth | std | sparse points | warped-pair |Δ|/depth.  All (C, H, W) of one frame."""
    masked = image.detach().float().cpu() * mask.cpu().float()
    return torch.cat(
        [
            masked,
            colorize(depth, mask),
            colorize(std, mask, "magma"),
            overlay_points(masked, sparse_valid),
            colorize(rel_error, error_valid, "inferno"),
        ],
        dim=2,
    )

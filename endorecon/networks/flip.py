"""Flip averaging (inference only): a frame's prediction combined with its mirror image's.

The network is trained with horizontal-flip augmentation (``data.augment.p_flip``), so
its prediction for the mirrored frame, mirrored back, is a second estimate of the same
depth.  The two are combined as the moment-matched Gaussian of their equal-weight mixture:

    depth = (d_a + d_b) / 2,   std² = (σ_a² + σ_b²) / 2 + ((d_a − d_b) / 2)²,

so where the two disagree the std grows.  A departure from the paper (its network is
run once per frame); on the phantom it lowered every held-out patient's AbsRel and raised
the std-error correlation (README).  Cost: a second forward pass at inference.
"""

from __future__ import annotations

from typing import Callable

import torch

from endorecon.geometry._checks import check_shape


def combine_predictions(depth_a: torch.Tensor, std_a: torch.Tensor, depth_b: torch.Tensor,
                        std_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and std of the equal-weight mixture of N(depth_a, std_a²) and N(depth_b, std_b²).

    Args:
        depth_a, std_a, depth_b, std_b: (B,1,H,W), all the same shape.
    Returns:
        depth, std: (B,1,H,W).
    """
    shape = check_shape(depth_a, "depth_a", (None, 1, None, None))
    for x, name in ((std_a, "std_a"), (depth_b, "depth_b"), (std_b, "std_b")):
        check_shape(x, name, shape)
    depth = 0.5 * (depth_a + depth_b)
    var = 0.5 * (std_a * std_a + std_b * std_b) + 0.25 * (depth_a - depth_b) ** 2
    return depth, torch.sqrt(var)


def predict_flip_averaged(net: Callable, images: torch.Tensor,
                          mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """``net(images, mask)`` combined with ``net`` of the horizontally mirrored images (mirrored back).

    Args:
        net: callable (B,3,H,W), (B,1,H,W) or None -> depth, std, each (B,1,H,W).
        images: (B,3,H,W).  mask: (B,1,H,W) or None.
    Returns:
        depth, std: (B,1,H,W), see :func:`combine_predictions`.
    """
    B, _, H, W = check_shape(images, "images", (None, 3, None, None))
    if mask is not None:
        check_shape(mask, "mask", (B, 1, H, W))
    depth_a, std_a = net(images, mask)
    depth_b, std_b = net(torch.flip(images, [-1]), None if mask is None else torch.flip(mask, [-1]))
    return combine_predictions(depth_a, std_a, torch.flip(depth_b, [-1]), torch.flip(std_b, [-1]))

"""Per-voxel maths of the adaptive TSDF: pure torch, no Open3D.

The adaptive fusion (Liu et al., after Zach et al.) differs from a plain TSDF
in two places:

* the truncation distance of a pixel comes from the predicted depth std:
  ``trunc = clamp(k * sigma, m * voxel, M * voxel)``; the floor of ``m`` voxels
  closes holes at grazing angles where ``k * sigma`` alone is under a voxel;
* observations are merged by exponential averaging with rate
  ``r = max(C1, min(C2, S^2 / (S^2 + Sigma^2)))`` (S: voxel's accumulated std,
  Sigma: the new observation's std); a fresh voxel (weight 0) takes the
  observation as is (r = 1).

The voxel std is updated with the same rate, in one of two ways (``std_mode``):

* ``propagate`` (default): the std of the averaged estimate itself,
  ``S'^2 = (1 - r)^2 S^2 + r^2 Sigma^2`` (independent errors). With r equal to
  the unclamped ``S^2 / (S^2 + Sigma^2)`` this is the inverse-variance
  (Kalman) update ``S'^2 = S^2 Sigma^2 / (S^2 + Sigma^2)``: S shrinks as
  observations agree, r falls like 1 / n, and the C1 floor turns the average
  into a forgetting one (steady state S^2 = r Sigma^2 / (2 - r)).
* ``average``: the same exponential average as the tsdf and colour,
  ``S' = (1 - r) S + r Sigma``; S stays between the stds that reached the
  voxel, so r hovers near 1/2 for similar stds and noise is averaged over only
  a few frames (measured: less accurate, see benchmarks/fusion.py).

``weight`` counts the observations (it only decides "fresh" and the mesh
threshold, it never weights the average).

Voxel-to-pixel projection is inlined in :func:`integrate_blocks` (rather than
calling ``endorecon.geometry.project``) so that ``torch.compile`` fuses the
whole per-voxel chain into one loop over voxels.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["averaging_rate", "truncation", "integrate_blocks", "integrate_blocks_", "clean_frame", "erode_mask",
           "local_voxel_offsets"]


def averaging_rate(acc_std: Tensor, obs_std: Tensor, c1: Tensor | float, c2: Tensor | float) -> Tensor:
    """Exponential-averaging rate ``r = max(C1, min(C2, S^2 / (S^2 + Sigma^2)))``.

    Args:
        acc_std: S, the voxel's accumulated std, any shape.
        obs_std: Sigma, the new observation's std, broadcastable to ``acc_std``.
        c1, c2: lower and upper bound of the rate (0 < c1 <= c2 <= 1).

    Returns:
        r, same shape as the broadcast inputs, in [c1, c2].
    """
    s2 = acc_std * acc_std
    ratio = s2 / (s2 + obs_std * obs_std).clamp_min(1e-30)
    return torch.minimum(torch.maximum(ratio, torch.as_tensor(c1, dtype=ratio.dtype)), torch.as_tensor(c2, dtype=ratio.dtype))


def truncation(obs_std: Tensor, k: Tensor | float, trunc_min: Tensor | float, trunc_max: Tensor | float) -> Tensor:
    """Per-pixel truncation distance ``clamp(k * sigma, trunc_min, trunc_max)`` (world units)."""
    t = obs_std * k
    return torch.minimum(torch.maximum(t, torch.as_tensor(trunc_min, dtype=t.dtype)), torch.as_tensor(trunc_max, dtype=t.dtype))


def local_voxel_offsets(resolution: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """(R^3, 3) in-block voxel coordinates in Open3D's order: index = x + r (y + r z)."""
    r = torch.arange(resolution, dtype=dtype, device=device)
    z, y, x = torch.meshgrid(r, r, r, indexing="ij")
    return torch.stack([x, y, z], dim=-1).reshape(-1, 3)


def integrate_blocks(
    block_keys: Tensor,
    tsdf: Tensor,
    weight: Tensor,
    std: Tensor,
    color: Tensor,
    local: Tensor,
    depth: Tensor,
    depth_std: Tensor,
    image: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    params: Tensor,
    return_rate: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """Fuse one frame into the voxels of N blocks; returns the new block values.

    Voxel v of block b sits at ``(block_keys[b] * res + local[v]) * voxel``
    (Open3D's convention: voxel values live at grid points, not cell centres).
    A voxel is updated when it projects inside the image onto a pixel with
    valid depth ``0 < d <= depth_max`` (nearest pixel, pixel-centre K) and
    lies at most one truncation distance behind that depth.

    Args:
        block_keys: (N, 3) integer block coordinates.
        tsdf, weight, std: (N, R) current voxel values, R = res^3.
        color: (N, R, 3) current voxel colours.
        local: (R, 3) float in-block voxel offsets (:func:`local_voxel_offsets`).
        depth: (H, W) z-depth, 0 where invalid (NaN/inf/masked already zeroed).
        depth_std: (H, W) predicted std of the depth, > 0 where depth is valid.
        image: (H, W, 3) colour in [0, 1].
        K: (3, 3) intrinsics, pixel-centre convention.
        cam_from_world: (4, 4).
        params: (9,) float tensor [voxel, res, c1, c2, k, trunc_min, trunc_max, depth_max,
            propagate] (propagate = 1: std_mode "propagate", 0: "average")
            (a tensor so that changing a value does not recompile).

    Returns:
        (tsdf, weight, std, color, rate): new values, shapes as the inputs;
        ``rate`` (N, R) is the rate applied (0 where the voxel was not updated,
        1 where it was fresh), None unless ``return_rate``.
    """
    H, W = depth.shape
    voxel, res, c1, c2, k, tmin, tmax, dmax, propagate = params.unbind(0)
    pts = (block_keys.to(local.dtype)[:, None, :] * res + local[None]) * voxel  # (N, R, 3) world
    R_ = cam_from_world[:3, :3].to(local.dtype)
    t_ = cam_from_world[:3, 3].to(local.dtype)
    xc = pts[..., 0] * R_[0, 0] + pts[..., 1] * R_[0, 1] + pts[..., 2] * R_[0, 2] + t_[0]
    yc = pts[..., 0] * R_[1, 0] + pts[..., 1] * R_[1, 1] + pts[..., 2] * R_[1, 2] + t_[1]
    zc = pts[..., 0] * R_[2, 0] + pts[..., 1] * R_[2, 1] + pts[..., 2] * R_[2, 2] + t_[2]
    zsafe = torch.where(zc > 0, zc, torch.ones_like(zc))
    u = K[0, 0] * xc / zsafe + K[0, 1] * yc / zsafe + K[0, 2]
    v = K[1, 1] * yc / zsafe + K[1, 2]
    # nearest pixel in the pixel-centre convention: pixel i covers [i - 0.5, i + 0.5)
    ui = torch.floor(u + 0.5)
    vi = torch.floor(v + 0.5)
    inside = (zc > 0) & (ui >= 0) & (ui <= W - 1) & (vi >= 0) & (vi <= H - 1)
    pix = (vi.clamp(0, H - 1) * W + ui.clamp(0, W - 1)).long()
    pix = torch.where(inside, pix, torch.zeros_like(pix))

    d = depth.reshape(-1)[pix]
    sig = depth_std.reshape(-1)[pix]
    col = image.reshape(-1, 3)[pix]
    trunc = truncation(sig, k, tmin, tmax)
    sdf = d - zc
    valid = inside & (d > 0) & (d <= dmax) & (sdf >= -trunc)
    obs = torch.clamp(sdf / trunc, max=1.0)

    fresh = weight <= 0
    rate = averaging_rate(std, sig, c1, c2)
    rate = torch.where(fresh, torch.ones_like(rate), rate)
    rate = torch.where(valid, rate, torch.zeros_like(rate))

    new_tsdf = tsdf + rate * (obs - tsdf)
    keep = 1.0 - rate
    new_std = torch.where(propagate > 0.5, torch.sqrt(keep * keep * std * std + rate * rate * sig * sig), std + rate * (sig - std))
    new_color = color + rate[..., None] * (col - color)
    new_weight = weight + valid.to(weight.dtype)
    return new_tsdf, new_weight, new_std, new_color, (rate if return_rate else None)


def integrate_blocks_(
    tsdf_all: Tensor,
    weight_all: Tensor,
    std_all: Tensor,
    color_all: Tensor,
    buf_index: Tensor,
    block_keys: Tensor,
    local: Tensor,
    depth: Tensor,
    depth_std: Tensor,
    image: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    params: Tensor,
) -> None:
    """In-place :func:`integrate_blocks` on a grid's buffers (gather, update, scatter).

    Args:
        tsdf_all, weight_all, std_all: (capacity, R) voxel buffers, updated in place.
        color_all: (capacity, R, 3), updated in place.
        buf_index: (N,) int64 buffer rows of the N blocks (unique).
        Others: as :func:`integrate_blocks`.

    Under ``torch.compile`` gather, maths and scatter fuse into one loop.
    """
    t, w, s, c, _ = integrate_blocks(block_keys, tsdf_all[buf_index], weight_all[buf_index], std_all[buf_index],
                                     color_all[buf_index], local, depth, depth_std, image, K, cam_from_world, params)
    tsdf_all[buf_index] = t
    weight_all[buf_index] = w
    std_all[buf_index] = s
    color_all[buf_index] = c


def erode_mask(mask: Tensor, radius_px: int) -> Tensor:
    """Drop the pixels within ``radius_px`` (Euclidean) of an invalid pixel or of the image border.

    The outer pixels of the endoscope's field of view are darkened by the black border (optics, resizing),
    and a network reads darker as farther: fusing them biases the open edge of the mesh.

    Args:
        mask: (H, W) bool, True = valid.
        radius_px: erosion radius in pixels (0 = unchanged).
    Returns:
        (H, W) bool, a subset of ``mask``.
    """
    if mask.ndim != 2 or mask.dtype != torch.bool:
        raise ValueError(f"mask must be (H, W) bool, got {tuple(mask.shape)} {mask.dtype}")
    r = int(radius_px)
    if r < 0:
        raise ValueError(f"radius_px must be >= 0, got {radius_px}")
    if r == 0:
        return mask
    y, x = torch.meshgrid(torch.arange(-r, r + 1), torch.arange(-r, r + 1), indexing="ij")
    disc = ((x * x + y * y) <= r * r).to(torch.float32).to(mask.device)[None, None]
    # outside the image counts as invalid: the network sees zero padding there
    invalid = torch.nn.functional.pad((~mask).to(torch.float32)[None, None], (r, r, r, r), value=1.0)
    near_invalid = torch.nn.functional.conv2d(invalid, disc)[0, 0] > 0.5
    return mask & ~near_invalid


def clean_frame(
    depth: Tensor, depth_std: Tensor | None, image: Tensor, mask: Tensor | None, params: Tensor
) -> tuple[Tensor, Tensor | None, Tensor, Tensor]:
    """Zero the depth of unusable pixels and bound the truncation band of a frame.

    A pixel is unusable when its depth is NaN/inf/<= 0/> depth_max, its std is
    NaN/inf/<= 0, or the mask is False.

    Args:
        depth: (H, W) float32.
        depth_std: (H, W) float32, or None (plain TSDF).
        image: (H, W, 3) float32, NaN -> 0, clamped to [0, 1].
        mask: (H, W) bool or None.
        params: as :func:`integrate_blocks`.

    Returns:
        (depth, std, image, trunc_max): cleaned inputs (std 1 where unusable,
        to keep the voxel maths finite) and the widest truncation of a usable
        pixel as a 0-d tensor (0 when no pixel is usable).
    """
    voxel, res, c1, c2, k, tmin, tmax, dmax, _ = params.unbind(0)
    valid = torch.isfinite(depth) & (depth > 0) & (depth <= dmax)
    if mask is not None:
        valid = valid & mask
    if depth_std is not None:
        ok = torch.isfinite(depth_std) & (depth_std > 0)
        valid = valid & ok
        depth_std = torch.where(ok, depth_std, torch.ones_like(depth_std))
        widest = torch.where(valid, truncation(depth_std, k, tmin, tmax), torch.zeros_like(depth_std)).amax()
    else:
        widest = torch.where(valid.any(), tmin, torch.zeros_like(tmin))
    depth = torch.where(valid, depth, torch.zeros_like(depth))
    image = torch.nan_to_num(image, 0.0, 0.0, 0.0).clamp(0.0, 1.0)
    return depth, depth_std, image, widest

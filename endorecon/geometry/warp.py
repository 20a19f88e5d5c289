"""Dense correspondences from depth: flow, bilinear sampling and depth warping.

The Depth Warping Layer of the method: frame j's depth is brought into frame i
by following i's pixels into j (with i's depth and the relative pose), sampling
j's depth there, and expressing that surface point in i's camera frame.  The
result is directly comparable with i's own depth (Depth Consistency Loss).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from endorecon.geometry._checks import check_shape
from endorecon.geometry.camera import pixel_grid, project, unproject

# Bilinear weight that may fall on pixels without depth before a warped sample counts as invalid
# (round-off at the image border; the sample is renormalised by the rest).
SUPPORT_TOL = 1e-3


def sample_bilinear(image: torch.Tensor, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample an image at pixel coordinates (pixel-centre convention), bilinear, zeros outside.

    Args:
        image: (B, C, H, W).
        uv: (B, h, w, 2) pixel coordinates (u = column, v = row).
    Returns:
        values: (B, C, h, w).
        inside: (B, 1, h, w) bool, True where uv lies within the pixel centres' hull [0, W-1] x [0, H-1]
            (± 1e-4 pixel).
    """
    B, C, H, W = check_shape(image, "image", (None, None, None, None))
    check_shape(uv, "uv", (B, None, None, 2))
    # align_corners=True maps -1/+1 to the centres of the border pixels, matching integer pixel centres.
    gx = 2.0 * uv[..., 0] / max(W - 1, 1) - 1.0
    gy = 2.0 * uv[..., 1] / max(H - 1, 1) - 1.0
    grid = torch.stack([gx, gy], dim=-1).to(image.dtype)
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    # A small tolerance so that a point on a border pixel's centre does not flip with round-off.
    tol = 1e-4
    inside = (uv[..., 0] >= -tol) & (uv[..., 0] <= W - 1 + tol) & (uv[..., 1] >= -tol) & (uv[..., 1] <= H - 1 + tol)
    return out, inside[:, None]


def _points_in_j(depth_i: torch.Tensor, K: torch.Tensor, cam_j_from_cam_i: torch.Tensor):
    B, _, H, W = check_shape(depth_i, "depth_i", (None, 1, None, None))
    check_shape(K, "K", (B, 3, 3))
    check_shape(cam_j_from_cam_i, "cam_j_from_cam_i", (B, 4, 4))
    X_i = unproject(depth_i, K).flatten(2).transpose(1, 2)  # (B, HW, 3)
    R, t = cam_j_from_cam_i[:, :3, :3], cam_j_from_cam_i[:, :3, 3]
    X_j = X_i @ R.transpose(1, 2) + t[:, None]
    uv_j, z_j = project(X_j, K)
    return X_j, uv_j.view(B, H, W, 2), z_j.view(B, 1, H, W)


def flow_from_depth(
    depth_i: torch.Tensor, K: torch.Tensor, cam_j_from_cam_i: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense optical flow from frame i to frame j implied by i's depth and the relative pose.

    Args:
        depth_i: (B, 1, H, W) z-depth of frame i.
        K: (B, 3, 3) pixel-centre intrinsics (shared by both frames).
        cam_j_from_cam_i: (B, 4, 4).
    Returns:
        flow: (B, 2, H, W) pixel displacement (du, dv) of each pixel of i into j.
        z_j: (B, 1, H, W) z-depth of i's points in frame j (<= 0: behind camera j).
    """
    B, _, H, W = check_shape(depth_i, "depth_i", (None, 1, None, None))
    _, uv_j, z_j = _points_in_j(depth_i, K, cam_j_from_cam_i)
    uv_i = pixel_grid(H, W, depth_i.device, depth_i.dtype)
    return (uv_j - uv_i).permute(0, 3, 1, 2), z_j


def warp_depth(
    depth_j: torch.Tensor,
    depth_i: torch.Tensor,
    K: torch.Tensor,
    cam_j_from_cam_i: torch.Tensor,
    std_j: torch.Tensor | None = None,
    min_depth: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Frame j's depth (and std) expressed in frame i, at frame i's pixels.

    For each pixel p of i: X = depth_i(p) K⁻¹ p is moved into j, projected to
    p_j, and j's depth d_j is sampled there; the surface point of j on that ray,
    Y_j = X_j · d_j / z_j, is moved back into i and its z is returned.  Where
    both depths agree, the output equals ``depth_i``.

    Args:
        depth_j: (B, 1, H, W) z-depth of frame j.
        depth_i: (B, 1, H, W) z-depth of frame i (defines the correspondences).
        K: (B, 3, 3) pixel-centre intrinsics.
        cam_j_from_cam_i: (B, 4, 4).
        std_j: optional (B, 1, H, W) std of depth_j, propagated linearly.
    Returns:
        depth_j_in_i: (B, 1, H, W), 0 where invalid.
        valid: (B, 1, H, W) bool: inside j's image, in front of both cameras, both depths finite and > min_depth,
            j's sample drawn (all but ``SUPPORT_TOL`` of its bilinear weight) from pixels with depth.
        std_j_in_i: (B, 1, H, W) or None.
    """
    B, _, H, W = check_shape(depth_j, "depth_j", (None, 1, None, None))
    check_shape(depth_i, "depth_i", (B, 1, H, W))
    X_j, uv_j, z_j = _points_in_j(depth_i, K, cam_j_from_cam_i)
    # A sample that blends in a pixel without depth (<= min_depth: a hole, a masked-out pixel; or not finite)
    # is no surface: require (almost) all of the bilinear weight on pixels with depth, and renormalise by it.
    has_depth = torch.isfinite(depth_j) & (depth_j > min_depth)
    d_j, inside = sample_bilinear(torch.where(has_depth, depth_j, torch.zeros_like(depth_j)), uv_j)
    support, _ = sample_bilinear(has_depth.to(depth_j.dtype), uv_j)
    full = support > 1.0 - SUPPORT_TOL
    d_j = torch.where(full, d_j / torch.where(full, support, torch.ones_like(support)), torch.zeros_like(d_j))
    zj_safe = torch.where(z_j > min_depth, z_j, torch.ones_like(z_j))
    X_j = X_j.transpose(1, 2).view(B, 3, H, W)
    R, t = cam_j_from_cam_i[:, :3, :3], cam_j_from_cam_i[:, :3, 3]
    # z in i of Y = Rᵀ(Y_j − t): third row of Rᵀ is R[:, :, 2].
    r3 = R[:, :, 2].view(B, 3, 1, 1)
    a = (r3 * X_j).sum(1, keepdim=True) / zj_safe  # d z_i / d d_j
    z_i = a * d_j - (r3[:, :, 0, 0] * t).sum(-1).view(B, 1, 1, 1)
    valid = (inside & (z_j > min_depth) & (d_j > min_depth) & (depth_i > min_depth) & (z_i > min_depth)
             & torch.isfinite(depth_i) & torch.isfinite(z_i))
    out = torch.where(valid, z_i, torch.zeros_like(z_i))
    std_out = None
    if std_j is not None:
        check_shape(std_j, "std_j", (B, 1, H, W))
        s_j, _ = sample_bilinear(std_j, uv_j)
        s_j = s_j / torch.where(full, support, torch.ones_like(support))
        std_out = torch.where(valid, (a * s_j).abs(), torch.zeros_like(s_j))
    return out, valid, std_out

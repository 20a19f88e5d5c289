"""Pinhole intrinsics, projection and back-projection.

Pixel convention: (u, v) = (column, row) and **(0, 0) is the centre of the
top-left pixel**, as in kornia and OpenCV.  COLMAP and Open3D put (0, 0) at the
top-left *corner*; :func:`to_corner_convention` / :func:`from_corner_convention`
convert at those boundaries (cx, cy ± 0.5) and nowhere else.
"""

from __future__ import annotations

import torch
from kornia.geometry.depth import depth_to_3d_v2

from endorecon.geometry._checks import check_shape


def _k(K: torch.Tensor) -> torch.Tensor:
    check_shape(K, "K", (None, 3, 3))
    return K


def scale_intrinsics(K: torch.Tensor, scale_x: float, scale_y: float) -> torch.Tensor:
    """Intrinsics after resizing the image by (scale_x, scale_y).

    With pixel centres at integers, a pixel edge sits at -0.5, so
    c' = (c + 0.5)·s − 0.5 and f' = f·s.

    Args:
        K: (B, 3, 3).
    Returns:
        (B, 3, 3).
    """
    _k(K)
    S = torch.tensor([[scale_x, 0.0, 0.5 * scale_x - 0.5], [0.0, scale_y, 0.5 * scale_y - 0.5], [0.0, 0.0, 1.0]],
                     dtype=K.dtype, device=K.device)
    return S @ K


def crop_intrinsics(K: torch.Tensor, x0: float, y0: float) -> torch.Tensor:
    """Intrinsics after cropping the image at column ``x0``, row ``y0`` (the new (0, 0)).

    Args:
        K: (B, 3, 3).
    Returns:
        (B, 3, 3).
    """
    _k(K)
    K = K.clone()
    K[:, 0, 2] = K[:, 0, 2] - x0
    K[:, 1, 2] = K[:, 1, 2] - y0
    return K


def to_corner_convention(K: torch.Tensor) -> torch.Tensor:
    """Pixel-centre intrinsics -> corner-convention intrinsics (COLMAP, Open3D): cx, cy + 0.5.

    Accepts a (3, 3) or (B, 3, 3) tensor or numpy array and returns the same kind.
    """
    return _shift_principal_point(K, 0.5)


def from_corner_convention(K: torch.Tensor) -> torch.Tensor:
    """Corner-convention intrinsics (COLMAP, Open3D) -> pixel-centre intrinsics: cx, cy − 0.5."""
    return _shift_principal_point(K, -0.5)


def _shift_principal_point(K, delta: float):
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"K must be (..., 3, 3), got {tuple(K.shape)}")
    K = K.clone() if isinstance(K, torch.Tensor) else K.copy()
    K[..., 0, 2] += delta
    K[..., 1, 2] += delta
    return K


def project(points_cam: torch.Tensor, K: torch.Tensor, eps: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """Project camera-frame points to pixels.

    Args:
        points_cam: (B, N, 3) points in the camera frame.
        K: (B, 3, 3) pixel-centre intrinsics.
    Returns:
        uv: (B, N, 2) pixel coordinates (u = column, v = row).
        z: (B, N) z-depth (points with z <= eps project with z clamped to eps).
    """
    B = check_shape(points_cam, "points_cam", (None, None, 3))[0]
    check_shape(K, "K", (B, 3, 3))
    z = points_cam[..., 2]
    zc = z.clamp(min=eps)
    x = points_cam[..., 0] / zc
    y = points_cam[..., 1] / zc
    u = K[:, None, 0, 0] * x + K[:, None, 0, 1] * y + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * y + K[:, None, 1, 2]
    return torch.stack([u, v], dim=-1), z


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H, W, 2) grid of pixel-centre coordinates (u, v) = (column, row)."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype), torch.arange(width, device=device, dtype=dtype), indexing="ij"
    )
    return torch.stack([u, v], dim=-1)


def unproject(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Back-project a z-depth map to camera-frame points.

    Args:
        depth: (B, 1, H, W) z-depth.
        K: (B, 3, 3) pixel-centre intrinsics.
    Returns:
        (B, 3, H, W) points in the camera frame.
    """
    B, _, H, W = check_shape(depth, "depth", (None, 1, None, None))
    check_shape(K, "K", (B, 3, 3))
    # kornia's grid has pixel centres at integers, as ours; it ignores the skew K[0, 1], which project() applies:
    # u = fx x + s y + cx, so x = x_kornia - s y / fx.
    # (Always applied, also at s = 0: so that the gradient w.r.t. K[0, 1] is that of project's inverse.)
    pts = depth_to_3d_v2(depth[:, 0], K).permute(0, 3, 1, 2)
    x = pts[:, 0:1] - (K[:, 0, 1] / K[:, 0, 0]).view(B, 1, 1, 1) * pts[:, 1:2]
    return torch.cat([x, pts[:, 1:]], 1)


def mask_bbox_crop(mask: torch.Tensor, multiple: int = 64) -> tuple[int, int, int, int]:
    """Crop window (x0, y0, width, height) around a mask's valid pixels, sides rounded down to ``multiple``.

    The original method downsamples frames and crops the endoscope mask's bounding box to
    a multiple of 64 so that the encoder-decoder's strides divide it; the window is
    centred on the bounding box and kept inside the image.

    Args:
        mask: (H, W) bool.
    """
    check_shape(mask, "mask", (None, None))
    H, W = mask.shape
    rows = torch.nonzero(mask.any(dim=1)).flatten()
    cols = torch.nonzero(mask.any(dim=0)).flatten()
    if len(rows) == 0:
        raise ValueError("mask has no valid pixel")
    y0, y1 = int(rows[0]), int(rows[-1]) + 1
    x0, x1 = int(cols[0]), int(cols[-1]) + 1
    h = max(multiple, ((y1 - y0) // multiple) * multiple)
    w = max(multiple, ((x1 - x0) // multiple) * multiple)
    if h > H or w > W:
        raise ValueError(f"mask bounding box is smaller than one {multiple}-pixel block in a {W}x{H} image")
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    y0 = int(min(max(round(cy - h / 2), 0), H - h))
    x0 = int(min(max(round(cx - w / 2), 0), W - w))
    return x0, y0, w, h

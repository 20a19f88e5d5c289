"""Analytic tests of the camera model (pixel-centre convention)."""

import numpy as np
import pytest
import torch

from endorecon.geometry import (
    crop_intrinsics,
    from_corner_convention,
    mask_bbox_crop,
    project,
    scale_intrinsics,
    to_corner_convention,
    unproject,
)


def K_(fx=100.0, fy=110.0, cx=39.5, cy=29.5, dtype=torch.float64):
    return torch.tensor([[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]], dtype=dtype)


def test_project_principal_axis_lands_on_principal_point():
    K = K_()
    uv, z = project(torch.tensor([[[0.0, 0.0, 5.0]]], dtype=torch.float64), K)
    assert torch.allclose(uv, torch.tensor([[[39.5, 29.5]]], dtype=torch.float64))
    assert torch.allclose(z, torch.tensor([[5.0]], dtype=torch.float64))


def test_unproject_fronto_parallel_plane_roundtrip():
    K = K_()
    depth = torch.full((1, 1, 6, 8), 3.0, dtype=torch.float64)
    pts = unproject(depth, K)
    assert pts.shape == (1, 3, 6, 8)
    assert torch.allclose(pts[:, 2], depth[:, 0])
    # pixel (u=5, v=2): x = (5 - cx) / fx * z
    assert torch.isclose(pts[0, 0, 2, 5], torch.tensor((5 - 39.5) / 100 * 3, dtype=torch.float64))
    uv, z = project(pts.flatten(2).transpose(1, 2), K)
    v, u = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
    assert torch.allclose(uv[0], torch.stack([u, v], -1).reshape(-1, 2).double())


def test_unproject_then_project_with_skew_is_the_identity():
    K = K_()
    K[0, 0, 1] = 2.0
    depth = torch.rand(1, 1, 6, 8, dtype=torch.float64) + 1.0
    uv, z = project(unproject(depth, K).flatten(2).transpose(1, 2), K)
    v, u = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
    torch.testing.assert_close(uv[0], torch.stack([u, v], -1).reshape(-1, 2).double())
    torch.testing.assert_close(z[0], depth.flatten())


def test_scale_intrinsics_pixel_centre_rule():
    # A 4x downsample: the centre of the 4x4 block of full-res pixels 0..3 is 1.5 -> new pixel 0.
    K = K_(cx=1.5, cy=1.5)
    K2 = scale_intrinsics(K, 0.25, 0.25)
    assert torch.allclose(K2[0, :2, 2], torch.zeros(2, dtype=torch.float64))
    assert torch.isclose(K2[0, 0, 0], torch.tensor(25.0, dtype=torch.float64))
    # A 3D point projects to the same place in the resized image as the resize of its full-res pixel.
    X = torch.tensor([[[0.3, -0.2, 2.0]]], dtype=torch.float64)
    uv_full, _ = project(X, K)
    uv_small, _ = project(X, K2)
    assert torch.allclose(uv_small, (uv_full + 0.5) * 0.25 - 0.5)


def test_crop_intrinsics_shifts_principal_point():
    K2 = crop_intrinsics(K_(), 10, 4)
    assert torch.allclose(K2[0, :2, 2], torch.tensor([29.5, 25.5], dtype=torch.float64))


def test_corner_convention_roundtrip_and_numpy():
    K = K_()
    Kc = to_corner_convention(K)
    assert torch.allclose(Kc[0, :2, 2], torch.tensor([40.0, 30.0], dtype=torch.float64))
    assert torch.allclose(from_corner_convention(Kc), K)
    Kn = np.eye(3)
    assert to_corner_convention(Kn)[0, 2] == 0.5 and Kn[0, 2] == 0.0  # no in-place change


def test_corner_convention_matches_colmap_pixel_centres():
    # COLMAP: the centre of pixel (col c, row r) is at (c + 0.5, r + 0.5).  A point on the ray through
    # pixel (3, 2)'s centre projects there in our convention and at (3.5, 2.5) with COLMAP's K.
    K = K_()
    Kc = to_corner_convention(K)
    X = unproject(torch.full((1, 1, 6, 8), 2.0, dtype=torch.float64), K)[:, :, 2, 3].reshape(1, 1, 3)
    uv_colmap = (Kc[0] @ (X[0, 0] / X[0, 0, 2]))[:2]
    assert torch.allclose(uv_colmap, torch.tensor([3.5, 2.5], dtype=torch.float64))


def test_shape_checks():
    with pytest.raises(ValueError, match="depth must have shape"):
        unproject(torch.ones(1, 6, 8), K_())
    with pytest.raises(ValueError, match="K must have shape"):
        project(torch.ones(2, 5, 3), K_())


def test_mask_bbox_crop_multiple_of_64():
    mask = torch.zeros(270, 480, dtype=torch.bool)
    yy, xx = torch.meshgrid(torch.arange(270.0), torch.arange(480.0), indexing="ij")
    mask[((xx - 240) ** 2 + (yy - 135) ** 2) < 130**2] = True
    x0, y0, w, h = mask_bbox_crop(mask, 64)
    assert w % 64 == 0 and h % 64 == 0 and w == 256 and h == 256
    assert 0 <= x0 and x0 + w <= 480 and 0 <= y0 and y0 + h <= 270


def test_gradcheck_project_unproject():
    K = K_().requires_grad_(True)
    pts = (torch.rand(1, 5, 3, dtype=torch.float64) + torch.tensor([0, 0, 1.0], dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda p, k: project(p, k)[0], (pts, K))
    depth = (torch.rand(1, 1, 3, 4, dtype=torch.float64) + 1).requires_grad_()
    assert torch.autograd.gradcheck(lambda d, k: unproject(d, k), (depth, K))

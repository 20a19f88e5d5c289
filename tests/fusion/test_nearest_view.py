"""The nearest-view check of the saved mesh: surface that no fused frame sees from near goes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from endorecon.fusion import AdaptiveTSDF, PlainTSDF, build_fusion, drop_far_only, surface_views
from endorecon.tasks.reconstruct import _far_only_line
from endorecon.utils.errors import InputError
from test_fusion import H, K, W, _grid_mesh, plane_depth, saved_per_setting


def _camera_at_z(c: float) -> torch.Tensor:
    """cam_from_world of a camera at (0, 0, c) looking along +z."""
    T = torch.eye(4, dtype=torch.float64)
    T[2, 3] = -c
    return T


def test_surface_views_nearest_is_the_smallest_depth_of_the_frames_on_the_point():
    """Cameras at z = 0, 0.5, -0.5 see the plane z = 2 at depth 2, 1.5, 2.5: a point on it is nearest at 1.5;
    a point in front of it (seen through) and one behind it (hidden) have no nearest view; a masked pixel
    says nothing."""
    centres = (0.0, 0.5, -0.5)
    T = torch.stack([_camera_at_z(c) for c in centres])
    depth = torch.stack([torch.full((H, W), 2.0 - c, dtype=torch.float64) for c in centres])
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [0.0, 0.0, 3.0]], dtype=torch.float64)
    on, through, nearest = surface_views(pts, depth, torch.as_tensor(K), T, tau=0.1)
    assert on.tolist() == [3, 0, 0] and through.tolist() == [0, 3, 0]
    assert nearest[0].item() == pytest.approx(1.5, abs=1e-12)
    assert torch.isinf(nearest[1:]).all()
    # the nearest frame masked at the point's pixel: the next nearest (2.0) counts
    mask = torch.ones(3, H, W, dtype=torch.bool)
    mask[1, int(round(K[1, 2])), int(round(K[0, 2]))] = False
    _, _, nearest_masked = surface_views(pts[:1], depth, torch.as_tensor(K), T, mask, tau=0.1)
    assert nearest_masked.item() == pytest.approx(2.0, abs=1e-12)


def test_drop_far_only_removes_the_triangles_at_vertices_seen_only_from_far():
    n = 6
    grid = _grid_mesh(n)
    nearest = np.ones(n * n)
    out, info = drop_far_only(grid, nearest, 1.0, 1.4)
    assert out is grid and info["removed"] == 0 and info["threshold"] == pytest.approx(1.4)
    nearest[2 * n + 2] = 2.0  # an inner vertex seen nearest at 2x the median: its six triangles go
    nearest[3 * n + 3] = np.inf  # no frame has this one on its surface: it says nothing and stays
    out, info = drop_far_only(grid, nearest, 1.0, 1.4)
    assert len(out.triangle.indices) == len(grid.triangle.indices) - 6 and info["removed"] == 6
    assert info["triangles"] == len(grid.triangle.indices) and info["median_depth"] == 1.0
    # the threshold scales with the median depth (SfM units are arbitrary)
    assert drop_far_only(grid, 10 * nearest, 10.0, 1.4)[1]["removed"] == 6
    assert drop_far_only(grid, nearest, 1.0, 2.0)[1]["removed"] == 0  # not above
    assert drop_far_only(grid, nearest, 1.0, None) == (grid, None)
    with pytest.raises(InputError, match="vertices"):
        drop_far_only(grid, nearest[:-1], 1.0, 1.4)
    with pytest.raises(InputError, match="median depth"):
        drop_far_only(grid, nearest, float("nan"), 1.4)


@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_saved_mesh_loses_surface_seen_only_from_far(cls, tmp_path):
    """Four frames see a near wall (depth 1) on the left 60 % of the image and a far wall (depth 3) on the rest.
    No frame sees the far wall nearer than 3x the median depth (1): the saved mesh drops it with the check
    (ratio 1.4) and keeps it without; the extracted mesh keeps it either way; the near wall stays whole."""
    voxel = 0.04
    poses = [np.eye(4) for _ in range(4)]
    for T, (dx, dy) in zip(poses, ((0.03, 0.0), (-0.03, 0.0), (0.0, 0.03), (0.0, -0.03))):
        T[0, 3], T[1, 3] = dx, dy
    depths = []
    for T in poses:
        d = plane_depth(T, (0.0, 0.0, 1.0), 1.0).copy()
        d[:, int(0.6 * W):] = plane_depth(T, (0.0, 0.0, 1.0), 3.0)[:, int(0.6 * W):]
        depths.append(d)
    stds = [np.full((H, W), 0.2 * voxel) for _ in poses]
    kw = {"compile": False} if cls is AdaptiveTSDF else {}
    saved, extracted, vol = saved_per_setting(cls, voxel, depths, stds, poses, tmp_path, "max_nearest_view_ratio", (None, 1.4))
    for ratio in (None, 1.4):
        assert (np.abs(extracted[ratio][:, 2] - 3.0) < 0.2).sum() > 10
    far = lambda p: (np.abs(p[:, 2] - 3.0) < 0.2).sum()  # noqa: E731
    near = lambda p: (np.abs(p[:, 2] - 1.0) < 0.1).sum()  # noqa: E731
    assert far(saved[None]) > 10 and far(saved[1.4]) == 0
    assert near(saved[1.4]) >= 0.97 * near(saved[None]) > 10
    assert vol.last_far_only["removed"] > 0 and vol.last_far_only["median_depth"] == pytest.approx(1.0, rel=0.05)
    for bad in (0.0, -1.0, "x", True, float("inf")):
        with pytest.raises(InputError, match="max_nearest_view_ratio"):
            cls(voxel, max_nearest_view_ratio=bad, **kw)


def test_build_fusion_passes_the_ratio_and_old_configs_have_no_check():
    base = dict(name="plain", voxel_size=0.02)
    assert build_fusion({**base, "max_nearest_view_ratio": 1.4}).max_nearest_view_ratio == 1.4
    assert build_fusion(base).max_nearest_view_ratio is None  # a run config from before the key


def test_report_line_of_the_nearest_view_check():
    assert "off" in _far_only_line(None)
    line = _far_only_line(dict(triangles=200, removed=20, ratio=1.4, threshold=1.4, median_depth=1.0))
    assert "20 of 200 triangles (10.0 %)" in line and "1.4x" in line

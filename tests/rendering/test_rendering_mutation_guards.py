"""Mutation guards for render_depth's mask handling (endorecon/rendering/raycast.py).

Helpers come from test_raycast.py."""

import numpy as np
import pytest

from endorecon.rendering import render_depth
from test_raycast import H, K, W, plane_mesh


def test_mask_of_the_wrong_size_is_refused():
    T = np.eye(4)[None]
    with pytest.raises(ValueError, match="mask must be"):
        render_depth(plane_mesh(5.0), K, T, H, W, mask=np.ones((H - 1, W), bool))
    with pytest.raises(ValueError, match="mask must be"):
        render_depth(plane_mesh(5.0), K, np.stack([np.eye(4)] * 2), H, W, mask=np.ones((3, H, W), bool))


def test_mask_in_the_projects_n1hw_convention():
    T = np.stack([np.eye(4)] * 2)
    mask = np.zeros((2, H, W), bool)
    mask[0, 5:20, 5:30] = True
    mask[1, 10:40, 20:60] = True
    ref = render_depth(plane_mesh(5.0, half=100.0), K, T, H, W, mask=mask)
    got = render_depth(plane_mesh(5.0, half=100.0), K, T, H, W, mask=mask[:, None])
    for a, b in zip(ref, got):
        np.testing.assert_array_equal(a, b)
    assert (got[1] == mask).all()


def test_a_frame_with_non_finite_intrinsics_comes_back_invalid():
    T = np.stack([np.eye(4)] * 4)
    Ks = np.stack([K] * 4)
    Ks[1, 0, 0] = np.nan
    Ks[2, 0, 0] = np.inf  # rays of x = 0 that would still hit the plane
    depth, valid = render_depth(plane_mesh(5.0, half=100.0), Ks, T, H, W)
    assert valid[0].all() and valid[3].all()
    assert not valid[1:3].any() and (depth[1:3] == 0).all()

"""Sparse-cloud cleaning and scale normalisation on analytic scenes."""

import numpy as np
import pytest

from endorecon.sfm.clean import clean_sparse, normalize_scale, project_all, smooth_visibility, sparse_depths

K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
H, W = 48, 64


def _translating_cameras(n=10, step=0.02):
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = -step * np.arange(n)  # camera moves along +x
    return T


def test_smooth_visibility_fills_short_gaps_only_where_candidate():
    vis = np.zeros((10, 3), bool)
    vis[[0, 3], 0] = True  # gap of 3 -> filled (window 3)
    vis[[0, 5], 1] = True  # gap of 5 -> not filled
    vis[[2, 4], 2] = True
    cand = np.ones((10, 3), bool)
    cand[3, 2] = False  # frame 3 not a candidate for point 2
    out = smooth_visibility(vis, cand, window=3)
    assert out[:4, 0].all() and not out[4:, 0].any()
    np.testing.assert_array_equal(out[:, 1], vis[:, 1])
    np.testing.assert_array_equal(out[:, 2], vis[:, 2])


def test_clean_rules():
    T = _translating_cameras()
    pts = np.array([
        [0.05, 0.0, 2.0],    # good, seen 0..8 with gaps -> smoothed
        [0.0, 0.05, 2.0],    # short track (2 frames) -> dropped
        [0.1, 0.1, 2.0],     # high reprojection error -> dropped
        [0.0, -0.1, 30.0],   # far (15x the median depth) -> its observations dropped -> point dropped
        [0.1, -0.05, 2.2],   # dark in frames >= 5
        [0.08, 0.02, 1.9],
    ])
    vis = [np.array([0, 2, 4, 6, 8]), np.array([0, 1]), np.array([0, 1, 2, 3]), np.array([0, 1, 2, 3]),
           np.arange(10), np.arange(10)]
    errors = np.array([0.5, 0.5, 5.0, 0.5, 0.5, 0.5])

    def gray(i):
        return np.full((H, W), 0.5 if i < 5 else 0.01)

    out_pts, out_vis, st = clean_sparse(T, K, np.ones((H, W), bool), pts, vis, errors, load_gray=gray,
                                        min_track_length=3, max_reproj_error=2.0, visibility_window=2,
                                        max_depth_ratio=3.0, min_brightness=0.05, min_observations=2)
    assert st["short_tracks"] == 1 and st["high_reproj_error"] == 1
    np.testing.assert_array_equal(st["kept_index"], [0, 4, 5])
    np.testing.assert_allclose(out_pts, pts[[0, 4, 5]])
    np.testing.assert_array_equal(out_vis[0], [0, 1, 2, 3, 4])  # smoothed 1,3; 5..8 dark
    np.testing.assert_array_equal(out_vis[1], [0, 1, 2, 3, 4])
    assert st["smoothing_added"] == 4  # frames 1, 3, 5, 7 of point 0


def test_clean_drops_points_outside_mask_and_behind():
    T = _translating_cameras(4)
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [0.5, 0.0, 2.0]])
    vis = [np.arange(4)] * 3
    mask = np.ones((H, W), bool)
    mask[:, 40:] = False
    uv, z = project_all(T, K, pts)
    assert (uv[:, 2, 0] >= 40).all() and (uv[:, 0, 0] < 40).all()  # point 2 lands on masked-out pixels
    out_pts, out_vis, st = clean_sparse(T, K, mask, pts, vis, None, None, min_track_length=3,
                                        visibility_window=1, min_brightness=0.0, min_observations=2)
    np.testing.assert_array_equal(st["kept_index"], [0])  # behind the cameras / outside the mask: gone
    np.testing.assert_array_equal(out_vis[0], np.arange(4))


def test_normalize_scale_median_depth_one_and_projections_unchanged():
    rng = np.random.default_rng(1)
    T = _translating_cameras(5, step=0.3)
    pts = rng.uniform([-1, -1, 3], [1, 1, 8], size=(50, 3))
    vis = [np.arange(5)] * 50
    T2, pts2, s = normalize_scale(T, pts, vis)
    assert np.median(sparse_depths(T2, pts2, vis)) == pytest.approx(1.0)
    assert s == pytest.approx(1.0 / np.median(sparse_depths(T, pts, vis)))
    uv1, _ = project_all(T, K, pts)
    uv2, _ = project_all(T2, K, pts2)
    np.testing.assert_allclose(uv1, uv2, atol=1e-9)

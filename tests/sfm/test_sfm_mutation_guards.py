"""Tests that mutations of endorecon/sfm/clean.py and metrics.py survived before (a review ran single-point mutations): each fails under its mutation."""

import numpy as np
import pytest

from endorecon.sfm.clean import clean_sparse

K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
H, W = 48, 64


def _still_cameras(n):
    return np.tile(np.eye(4), (n, 1, 1))


def test_track_length_and_reprojection_error_boundaries():
    # track length (and observations) exactly min_track_length (min_observations) is kept; error exactly max_reproj_error is kept, above it and NaN are not
    pts = np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0], [0.0, 0.1, 2.0], [0.1, 0.1, 2.0], [-0.1, 0.0, 2.0]])
    vis = [np.arange(3), np.arange(2), np.arange(3), np.arange(3), np.arange(3)]
    errors = np.array([0.5, 0.5, 2.0, 2.5, np.nan])
    _, _, st = clean_sparse(_still_cameras(3), K, np.ones((H, W), bool), pts, vis, errors, None, min_track_length=3,
                            max_reproj_error=2.0, visibility_window=1, min_brightness=0.0, min_observations=3)
    assert st["short_tracks"] == 1 and st["high_reproj_error"] == 2
    np.testing.assert_array_equal(st["kept_index"], [0, 2])


def test_far_rule_uses_the_median_depth_and_keeps_exactly_three_times_it():
    # six points at z=1, one at exactly 3 (kept: z <= 3 x median), one at 3.5 (dropped although
    # below 3 x the *mean* depth 3.69 of the frame), one at 20 (dropped)
    z = np.array([1.0] * 6 + [3.0, 3.5, 20.0])
    x = np.linspace(-0.3, 0.3, len(z))
    pts = np.stack([x * z, 0.05 * z, z], axis=1)
    vis = [np.arange(3)] * len(z)
    _, _, st = clean_sparse(_still_cameras(3), K, np.ones((H, W), bool), pts, vis, None, None, min_track_length=3,
                            visibility_window=1, max_depth_ratio=3.0, min_brightness=0.0, min_observations=2)
    np.testing.assert_array_equal(st["kept_index"], [0, 1, 2, 3, 4, 5, 6])
    assert st["far_observations"] == 6


def test_unregistered_frames_neither_observe_nor_bridge_gaps():
    # point seen in frames 0 and 3, frame 3 unregistered: no observation there, and no gap 0..3 to fill
    T = _still_cameras(5)
    T[3] = np.nan
    pts = np.array([[0.0, 0.0, 2.0]])
    _, vis, st = clean_sparse(T, K, np.ones((H, W), bool), pts, [np.array([0, 3])], None, None, min_track_length=2,
                              visibility_window=3, min_brightness=0.0, min_observations=1)
    np.testing.assert_array_equal(vis[0], [0])
    assert st["smoothing_added"] == 0


def test_normalize_scale_ignores_observations_behind_the_camera():
    from endorecon.sfm.clean import normalize_scale

    pts = np.array([[0.0, 0.0, -5.0], [0.0, 0.0, -4.0], [0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    vis = [np.array([0])] * 5
    _, _, s = normalize_scale(_still_cameras(1), pts, vis)
    assert s == 0.5  # 1 / median(1, 2, 3)


def _similar_trajectories(n=10, s=3.0, ref_dz=None):
    """ref (n, 4, 4) along a line (step 0.5, path 4.5) and est: the same cameras in a world x_ref = s R x_est + t;
    ref_dz: optional (n,) offsets of the reference centres along z (est keeps the straight line)."""
    from scipy.spatial.transform import Rotation

    def poses(dz):
        T = np.tile(np.eye(4), (n, 1, 1))
        for i in range(n):
            Rc = Rotation.from_rotvec([0.02 * i, -0.01 * i, 0.03 * i]).as_matrix()
            T[i, :3, :3] = Rc
            T[i, :3, 3] = -Rc @ np.array([0.5 * i, 0.0, dz[i]])
        return T

    line = poses(np.zeros(n))
    S = np.eye(4)
    S[:3, :3] = s * Rotation.from_rotvec([0.3, -0.7, 0.2]).as_matrix()
    S[:3, 3] = [1.0, 2.0, -3.0]
    D = np.diag([1 / s] * 3 + [1.0])
    est = np.stack([D @ r @ S for r in line])
    return (line if ref_dz is None else poses(np.asarray(ref_dz, float))), est


def test_trajectory_error_of_a_similar_trajectory_is_zero_and_path_is_exact():
    from endorecon.sfm.metrics import trajectory_error

    ref, est = _similar_trajectories()
    err = trajectory_error(est, ref)
    assert err["sim3"][0] == pytest.approx(3.0)
    assert err["path_length"] == pytest.approx(4.5)
    assert err["center_rmse"] < 1e-9 and err["rel_rotation_deg"] < 1e-6
    assert err["rel_translation_rel"] < 1e-9  # translations compared after the scale


def test_trajectory_error_known_rmse_and_skipped_reference_rows():
    from endorecon.sfm.metrics import trajectory_error

    # reference centres off the line by +-0.2 in a pattern orthogonal to any similarity: rmse exactly 0.2
    signs = np.array([1, -1, -1, 1, 1, -1, -1, 1, 1, -1, -1, 1], float)
    ref, est = _similar_trajectories(n=12, ref_dz=0.2 * signs)
    err = trajectory_error(est, ref)
    assert err["center_rmse"] == pytest.approx(0.2, rel=1e-6)
    ref, est = _similar_trajectories()
    ref[4] = np.nan  # unregistered in the reference only: skipped, not a NaN result
    err = trajectory_error(est, ref)
    assert err["frames"] == 9 and err["center_rmse"] < 1e-9


def test_project_all_gives_nan_for_unregistered_frames():
    from endorecon.sfm.clean import project_all

    T = _still_cameras(3)
    T[1] = np.nan
    uv, z = project_all(T, K, np.array([[0.0, 0.0, 2.0]]))
    assert np.isnan(uv[1]).all() and np.isnan(z[1]).all()  # not the principal point at z = 0
    assert np.isfinite(uv[[0, 2]]).all() and (z[[0, 2]] == 2.0).all()


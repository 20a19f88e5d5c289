"""Tests that mutations of endorecon/data survived before (a review ran single-point mutations): each fails under its mutation."""

import numpy as np

from endorecon.data.sparse import build_sparse_cache, nearest_pixel
from test_sparse import cameras, make_seq


def test_nearest_pixel_rounds_half_up_also_for_negatives():
    # pixel k covers [k - 0.5, k + 0.5): x.5 goes up (np.rint would round half to even)
    uv = np.array([[0.5, 1.5], [2.5, -0.5], [-1.5, 3.49]])
    np.testing.assert_array_equal(nearest_pixel(uv), [[1, 2], [3, 0], [-1, 3]])


def test_a_point_listed_twice_for_a_frame_is_one_observation():
    T = cameras(2)
    X = np.array([[0.0, 0.0, 10.0], [0.5, 0.2, 10.0]])
    cache = build_sparse_cache(make_seq(T, X, [np.array([0, 0, 1]), np.array([1, 0])]))
    assert cache.num_points(0) == 2 and cache.num_points(1) == 2
    ids, _, _ = cache.frame_points(0)
    np.testing.assert_array_equal(ids, [0, 1])
    uv_i, uv_j, _, _ = cache.pair_points(0, 1)
    assert len(uv_i) == len(uv_j) == 2

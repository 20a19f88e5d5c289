"""Sparse depth / flow maps against projections computed independently (numpy pinhole, analytic plane)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from endorecon.data.sequence import Sequence
from endorecon.data.sparse import (
    SparseCache,
    build_sparse_cache,
    load_or_build_sparse_cache,
    rasterize_points,
)
from endorecon.geometry import flow_from_depth
from endorecon.utils.errors import InputError

H, W = 64, 80
K = np.array([[60.0, 0.0, 39.2], [0.0, 52.0, 31.7], [0.0, 0.0, 1.0]])


def rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def cameras(n: int = 4) -> np.ndarray:
    """cam_from_world of n cameras sliding along x with a small yaw; world = camera 0."""
    return np.stack([pose(rot("y", 2.0 * k) @ rot("x", -1.0 * k), [-0.4 * k, 0.1 * k, 0.2 * k]) for k in range(n)])


def pinhole(T: np.ndarray, X: np.ndarray, K: np.ndarray = K) -> tuple[np.ndarray, np.ndarray]:
    """Independent reference projection: (P, 3) world points -> uv (P, 2), z (P,)."""
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return np.stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2], K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]], 1), Xc[:, 2]


def make_seq(T, X, vis, mask=None, name="s") -> Sequence:
    n = len(T)
    return Sequence(
        name=name, frame_paths=[f"f{k}.png" for k in range(n)], intrinsics=K, height=H, width=W,
        mask=np.ones((H, W), bool) if mask is None else mask, cam_from_world=T, points_xyz=X,
        visibility=vis, patient=0,
    )  # fmt: skip


def random_plane_points(rng, P: int = 60) -> np.ndarray:
    """Points of the plane z = 10 + 0.1 x (world = camera 0) inside camera 0's view."""
    u = rng.uniform(5, W - 6, P)
    v = rng.uniform(5, H - 6, P)
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    z = 10.0 / (1.0 - 0.1 * x)
    return np.stack([x * z, y * z, z], 1)


@pytest.fixture
def scene():
    rng = np.random.default_rng(0)
    T = cameras(4)
    X = random_plane_points(rng)
    vis = [np.arange(4) for _ in X]
    return T, X, vis


def test_depth_map_matches_independent_projection(scene):
    T, X, vis = scene
    cache = build_sparse_cache(make_seq(T, X, vis))
    for f in range(len(T)):
        uv, z = pinhole(T[f], X)
        depth, valid = cache.depth_map(f)
        assert depth.shape == (1, H, W) and depth.dtype == np.float32 and valid.dtype == bool
        inside = (np.floor(uv + 0.5) >= 0).all(1) & (np.floor(uv[:, 0] + 0.5) < W) & (np.floor(uv[:, 1] + 0.5) < H)
        px = np.floor(uv[inside] + 0.5).astype(int)
        # Each visible point's pixel holds the nearest z that lands there.
        for (c, r), zz in zip(px, z[inside]):
            assert valid[0, r, c]
            same = (px[:, 0] == c) & (px[:, 1] == r)
            np.testing.assert_allclose(depth[0, r, c], z[inside][same].min(), rtol=1e-6)
        assert valid.sum() == len({tuple(p) for p in px})
        assert not depth[~valid].any()
        ids, uv_c, z_c = cache.frame_points(f)
        np.testing.assert_allclose(uv_c, uv[ids], atol=1e-9)
        np.testing.assert_allclose(z_c, z[ids], rtol=1e-12)
    assert cache.num_points(0) == len(X)  # all inside frame 0 by construction


def test_flow_map_matches_projection_difference(scene):
    T, X, vis = scene
    vis = [v if k % 3 else np.array([0, 1]) for k, v in enumerate(vis)]  # some points only in frames 0, 1
    cache = build_sparse_cache(make_seq(T, X, vis))
    for i, j in [(0, 2), (2, 0), (1, 3), (0, 1)]:
        uv_i, _ = pinhole(T[i], X)
        uv_j, _ = pinhole(T[j], X)
        flow, valid = cache.flow_map(i, j)
        assert flow.shape == (2, H, W) and flow.dtype == np.float32
        both = np.array([i in v and j in v for v in vis])
        ok = both & (np.floor(uv_i + 0.5) >= 0).all(1) & (np.floor(uv_i[:, 0] + 0.5) < W)
        ok &= (np.floor(uv_j + 0.5) >= 0).all(1) & (np.floor(uv_j[:, 0] + 0.5) < W) & (np.floor(uv_j[:, 1] + 0.5) < H)
        px = np.floor(uv_i[ok] + 0.5).astype(int)
        assert valid.sum() == len({tuple(p) for p in px}) > 10
        for (c, r), d in zip(px, (uv_j - uv_i)[ok]):
            np.testing.assert_allclose(flow[:, r, c], d, atol=1e-4)
        assert not flow[:, ~valid[0]].any()


def test_flow_equals_flow_from_analytic_depth():
    """Points on pixel centres of frame 0 on a tilted plane: cache flow == flow_from_depth(analytic depth)."""
    n, d = np.array([0.1, -0.05, 1.0]), 12.0  # plane n . X = d in camera 0
    v, u = np.mgrid[0:H:3, 0:W:3].reshape(2, -1).astype(float)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], 1)
    X = rays * (d / (rays @ n))[:, None]
    T = cameras(3)
    cache = build_sparse_cache(make_seq(T, X, [np.arange(3)] * len(X)))
    vv, uu = np.mgrid[0:H, 0:W].astype(float)
    r = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], 0)
    depth0 = d / np.einsum("c,chw->hw", n, r) * r[2]
    depth_sparse, valid_d = cache.depth_map(0)
    np.testing.assert_allclose(depth_sparse[valid_d], depth0[valid_d[0]], rtol=1e-6)
    for j in (1, 2):
        Tj = torch.from_numpy(T[j] @ np.linalg.inv(T[0]))[None]
        ref, _ = flow_from_depth(torch.from_numpy(depth0)[None, None], torch.from_numpy(K)[None], Tj)
        flow, valid = cache.flow_map(0, j)
        assert valid.sum() > 100
        np.testing.assert_allclose(flow[:, valid[0]], ref[0].numpy()[:, valid[0]], atol=1e-4)


def test_drops_behind_outside_masked_and_unregistered():
    T = cameras(3)
    T[2] = np.nan  # unregistered
    X = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, -5.0], [100.0, 0.0, 10.0], [-2.0, 0.0, 10.0], [1.0, 0.5, 8.0]])
    mask = np.ones((H, W), bool)
    mask[:, : int(K[0, 2]) - 5] = False  # point 3 (u ~ 27) falls in the masked-out part in frame 0
    cache = build_sparse_cache(make_seq(T, X, [np.arange(3)] * len(X), mask=mask))
    ids0, _, _ = cache.frame_points(0)
    assert list(ids0) == [0, 4]  # 1 behind, 2 outside the image, 3 outside the mask
    assert cache.num_points(2) == 0
    depth, valid = cache.depth_map(2)
    assert not valid.any() and not depth.any()
    assert not cache.flow_map(0, 2)[1].any()


def test_collision_keeps_nearer_point():
    T = cameras(1)
    ray = np.array([0.3, -0.2, 1.0])
    X = np.stack([ray * 9.0, ray * 4.0, ray * 6.0])
    cache = build_sparse_cache(make_seq(T, X, [np.array([0])] * 3))
    depth, valid = cache.depth_map(0)
    assert valid.sum() == 1
    assert depth[valid][0] == pytest.approx(4.0, rel=1e-6)


def test_rasterize_pixel_centre_rounding():
    uv = np.array([[0.49, 0.0], [0.51, 2.0], [-0.51, 1.0], [W - 0.51, H - 1.0], [W - 0.49, 0.0]])
    img, valid = rasterize_points(uv, np.arange(5.0)[:, None] + 1, np.ones(5), H, W)
    assert valid[0, 0, 0] and img[0, 0, 0] == 1
    assert valid[0, 2, 1] and img[0, 2, 1] == 2
    assert valid[0, H - 1, W - 1] and img[0, H - 1, W - 1] == 4
    assert valid.sum() == 3  # -0.51 and W-0.49 round outside


def test_save_load_roundtrip(tmp_path, scene):
    T, X, vis = scene
    cache = build_sparse_cache(make_seq(T, X, vis))
    cache.save(tmp_path / "c.npz")
    back = SparseCache.load(tmp_path / "c.npz")
    for f in range(len(T)):
        for a, b in zip(cache.depth_map(f), back.depth_map(f)):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(cache.flow_map(0, 3)[0], back.flow_map(0, 3)[0])
    assert back.fingerprint == cache.fingerprint and len(back) == 4


def test_load_or_build_rebuilds_when_poses_change(tmp_path, scene):
    T, X, vis = scene
    path = tmp_path / "c.npz"
    seq = make_seq(T, X, vis)
    c1 = load_or_build_sparse_cache(seq, path)
    mtime = path.stat().st_mtime_ns
    c2 = load_or_build_sparse_cache(seq, path)
    assert path.stat().st_mtime_ns == mtime and c2.fingerprint == c1.fingerprint
    T2 = T.copy()
    T2[1, 0, 3] += 0.5
    c3 = load_or_build_sparse_cache(seq.replace(cam_from_world=T2), path)
    assert c3.fingerprint != c1.fingerprint
    assert not np.allclose(c3.frame_points(1)[1], c1.frame_points(1)[1])
    path.write_bytes(path.read_bytes()[:100])  # cut short: rebuilt (was a raw BadZipFile)
    assert load_or_build_sparse_cache(seq, path).fingerprint == c1.fingerprint


def test_bad_input(tmp_path, scene):
    T, X, vis = scene
    with pytest.raises(InputError, match="not found"):
        SparseCache.load(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"not an npz")
    with pytest.raises(InputError, match="corrupt"):
        SparseCache.load(tmp_path / "bad.npz")
    bad_vis = [np.array([0, 7])] + list(vis[1:])
    with pytest.raises(InputError, match="frame 7"):
        build_sparse_cache(make_seq(T, X, bad_vis))
    cache = build_sparse_cache(make_seq(T, X, vis))
    for bad in (9, -1, len(T)):  # -1 gave an empty map without the range check
        with pytest.raises(IndexError, match=f"frame {bad} out of range"):
            cache.depth_map(bad)
        with pytest.raises(IndexError, match=f"frame {bad} out of range"):
            cache.frame_points(bad)

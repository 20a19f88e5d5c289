"""Augmentations: camera-model consistency of flip/rotation, point-set transport, photometric ops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from endorecon.data.augment import (
    AugmentConfig,
    GeometricTransform,
    PairSample,
    apply_geometric,
    augment_pair,
    flip_transform,
    photometric,
    rotation_transform,
    sample_geometric,
)
from endorecon.data.datamodule import pair_to_batch
from endorecon.geometry import flow_from_depth
from endorecon.utils.errors import InputError

H, W = 48, 64
K = np.array([[50.0, 0.0, 30.3], [0.0, 44.0, 24.6], [0.0, 0.0, 1.0]])  # fx != fy on purpose


def rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


# cam_j_from_cam_i of the pair: a small motion.
T_JI = np.eye(4)
T_JI[:3, :3] = rot("y", 3.0) @ rot("z", 2.0)
T_JI[:3, 3] = [0.3, -0.1, 0.2]
PLANE_N, PLANE_D = np.array([0.15, -0.1, 1.0]), 10.0  # n . X = d in camera i


def proj(Xc: np.ndarray, K: np.ndarray) -> np.ndarray:
    return np.stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 1] * Xc[:, 1] / Xc[:, 2] + K[0, 2],
                     K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]], 1)  # fmt: skip


def plane_depth(K: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """Analytic (H, W) z-depth of the plane n . X = d seen by a camera with intrinsics K."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    r = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    return (d / (n @ r)).reshape(H, W)  # r_z = 1 (K upper triangular), so t = z


def sample_from_points(X_i: np.ndarray, mask=None, rng=None) -> PairSample:
    """A pair whose points (camera-i coordinates) are seen in both frames."""
    rng = rng or np.random.default_rng(0)
    X_j = X_i @ T_JI[:3, :3].T + T_JI[:3, 3]
    ids = np.arange(len(X_i))
    m = torch.ones(1, H, W, dtype=torch.bool) if mask is None else mask
    return PairSample(
        image_i=torch.from_numpy(rng.random((3, H, W))).float(), image_j=torch.from_numpy(rng.random((3, H, W))).float(),
        mask_i=m, mask_j=m.clone(), K=K.copy(), cam_j_from_cam_i=T_JI.copy(),
        ids_i=ids, uv_i=proj(X_i, K), z_i=X_i[:, 2], ids_j=ids.copy(), uv_j=proj(X_j, K), z_j=X_j[:, 2],
    )  # fmt: skip


def transforms() -> dict[str, GeometricTransform]:
    f = flip_transform(K, W)
    return {
        "flip": f,
        "rotate": rotation_transform(K, math.radians(8.0)),
        "flip+rotate": f.then(rotation_transform(f.K, math.radians(-6.0))),
    }


@pytest.mark.parametrize("name", ["flip", "rotate", "flip+rotate"])
def test_transform_is_a_camera_model_change(name):
    """Projecting M X with K' gives A (projection of X with K), and z is unchanged."""
    tf = transforms()[name]
    X = np.random.default_rng(1).uniform([-3, -3, 5], [3, 3, 15], (50, 3))
    np.testing.assert_allclose(proj(X @ tf.M.T, tf.K), tf.apply_uv(proj(X, K)), atol=1e-9)
    np.testing.assert_allclose((X @ tf.M.T)[:, 2], X[:, 2])
    assert np.allclose(tf.K[2], [0, 0, 1]) and abs(tf.K[1, 0]) < 1e-12
    np.testing.assert_allclose(tf.M @ tf.M.T, np.eye(3), atol=1e-12)
    P = tf.apply_pose(T_JI)
    assert np.linalg.det(P[:3, :3]) == pytest.approx(1.0)  # still a proper rigid motion


def test_flip_intrinsics_and_pose():
    tf = flip_transform(K, W)
    assert tf.K[0, 2] == pytest.approx(W - 1 - K[0, 2]) and tf.K[1, 2] == K[1, 2]
    F = np.diag([-1.0, 1, 1, 1])
    np.testing.assert_allclose(tf.apply_pose(T_JI), F @ T_JI @ F)
    np.testing.assert_allclose(tf.apply_vectors(np.array([[2.0, 3.0]])), [[-2.0, 3.0]])


def test_warp_pixel_convention():
    img = torch.rand(3, H, W)
    f = flip_transform(K, W)
    assert torch.equal(f.warp(img), torch.flip(img, dims=[-1]))
    assert torch.equal(f.warp(img, "nearest"), torch.flip(img, dims=[-1]))
    # The general path (kornia warp_affine) agrees with the flip up to float32 rounding.
    g = f.then(rotation_transform(f.K, 1e-9))
    torch.testing.assert_close(g.warp(img), torch.flip(img, dims=[-1]), atol=5e-5, rtol=0)
    # A linear image is reproduced exactly by bilinear warping: out(p') = in(A^-1 p').
    tf = rotation_transform(K, math.radians(9.0))
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    lin = (0.3 * u - 0.2 * v + 4.0)[None].float()
    out = tf.warp(lin)
    src = tf.inverse().apply_uv(torch.stack([u.flatten(), v.flatten()], 1).numpy())
    inside = (src[:, 0] >= 0) & (src[:, 0] <= W - 1) & (src[:, 1] >= 0) & (src[:, 1] <= H - 1)
    expect = 0.3 * src[:, 0] - 0.2 * src[:, 1] + 4.0
    np.testing.assert_allclose(out.flatten().numpy()[inside], expect[inside], atol=2e-3)
    assert inside.mean() > 0.7
    m = tf.warp(torch.ones(1, H, W, dtype=torch.bool))
    assert m.dtype == torch.bool and not m[0, 0, 0] and m[0, H // 2, W // 2]


@pytest.mark.parametrize("name", ["flip", "rotate", "flip+rotate"])
def test_transformed_pair_satisfies_geometry(name):
    """After the transform, sparse flow == flow_from_depth(analytic depth, K', pose') and sparse depth == analytic depth.

    The points are the plane's points under the *new* camera's pixel centres, so the comparison is exact.
    """
    tf = transforms()[name]
    n_new = tf.M @ PLANE_N  # the plane in the new camera frame
    v, u = np.mgrid[2 : H - 2 : 3, 2 : W - 2 : 3].reshape(2, -1).astype(float)
    rays = (np.linalg.inv(tf.K) @ np.stack([u, v, np.ones_like(u)])).T
    X_new = rays * (PLANE_D / (rays @ n_new))[:, None]
    X_i = X_new @ tf.M  # back to the original camera i: X = Mᵀ X'
    batch = pair_to_batch(apply_geometric(sample_from_points(X_i), tf), 0, 1)

    depth_new = plane_depth(tf.K, n_new, PLANE_D)
    valid_d = batch["sparse_valid_i"][0].numpy()
    assert valid_d.sum() > 200
    np.testing.assert_allclose(batch["sparse_depth_i"][0].numpy()[valid_d], depth_new[valid_d], rtol=1e-5)
    np.testing.assert_allclose(batch["K"].numpy(), tf.K, atol=1e-5)

    ref, _ = flow_from_depth(
        torch.from_numpy(depth_new)[None, None], torch.from_numpy(tf.K)[None],
        batch["cam_j_from_cam_i"].double()[None],
    )  # fmt: skip
    fv = batch["sparse_flow_valid_ij"][0].numpy()
    assert fv.sum() > 150
    np.testing.assert_allclose(batch["sparse_flow_ij"].numpy()[:, fv], ref[0].numpy()[:, fv], atol=2e-3)
    # ji is the reverse displacement, at j's pixels
    assert batch["sparse_flow_valid_ji"].sum() > 150


def test_augment_then_unaugment_gives_same_sparse_depth():
    rng = np.random.default_rng(3)
    X = rng.uniform([-4, -3, 8], [4, 3, 14], (400, 3))
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    mask[:, 3:-3, 4:-4] = True
    s = sample_from_points(X, mask)
    base = pair_to_batch(s, 0, 1)
    for name, tf in transforms().items():
        aug = apply_geometric(s, tf)
        moved = pair_to_batch(aug, 0, 1)
        assert not torch.equal(moved["sparse_depth_i"], base["sparse_depth_i"])
        back = pair_to_batch(apply_geometric(aug, tf.inverse()), 0, 1)
        v = back["sparse_valid_i"]
        assert (v & ~base["sparse_valid_i"]).sum() == 0
        assert v.sum() >= 0.7 * base["sparse_valid_i"].sum(), name
        assert torch.equal(back["sparse_depth_i"][v], base["sparse_depth_i"][v]), name
        fv = back["sparse_flow_valid_ij"]
        torch.testing.assert_close(back["sparse_flow_ij"][:, fv[0]], base["sparse_flow_ij"][:, fv[0]], atol=1e-4, rtol=0)
        np.testing.assert_allclose(back["cam_j_from_cam_i"].numpy(), T_JI, atol=1e-6)
        np.testing.assert_allclose(back["K"].numpy(), K, atol=1e-5)


def test_sim_depth_is_moved_exactly_by_a_flip_and_interpolated_by_a_roll():
    s = sample_from_points(np.array([[0.0, 0.0, 10.0]]))
    depth = torch.rand(1, H, W) + 5.0
    valid = torch.rand(1, H, W) > 0.3
    s.sim_depth_i, s.sim_valid_i = depth * valid, valid
    s.sim_depth_j, s.sim_valid_j = depth.clone(), torch.ones_like(valid)
    tf = flip_transform(K, W)
    out = apply_geometric(s, tf)
    assert torch.equal(out.sim_depth_i, torch.flip(depth * valid, dims=[-1]))
    assert torch.equal(out.sim_valid_i, torch.flip(valid, dims=[-1]))
    # A roll: each output pixel u' takes the label at A⁻¹u', interpolated (exact for a label linear in u, v);
    # nearest took the label of a pixel up to 0.7 px away.  Pixels whose sample touches an invalid one stay out.
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    linear = (5.0 + 0.05 * u + 0.08 * v)[None]
    holes = torch.ones_like(valid)
    holes[..., 5:9, 7:12] = False
    s.sim_depth_i, s.sim_valid_i = linear * holes, holes
    s.sim_depth_j, s.sim_valid_j = linear.clone(), torch.ones_like(valid)
    tf = rotation_transform(K, math.radians(7))
    rot = apply_geometric(s, tf)
    A_inv = np.linalg.inv(tf.A)
    src = np.stack([u.numpy().ravel(), v.numpy().ravel(), np.ones(H * W)]) .T @ A_inv.T
    expect = torch.from_numpy(5.0 + 0.05 * src[:, 0] + 0.08 * src[:, 1]).float().view(1, H, W)
    for d, ok in ((rot.sim_depth_i, rot.sim_valid_i), (rot.sim_depth_j, rot.sim_valid_j)):
        assert ok.float().mean() > 0.5
        torch.testing.assert_close(d[ok], expect[ok], atol=2e-4, rtol=0)
        assert (d[~ok] == 0).all()
    # the hole's neighbourhood is left out in i but kept in j
    inside = (src[:, 0] > 6.01) & (src[:, 0] < 11.99) & (src[:, 1] > 4.01) & (src[:, 1] < 8.99)
    inside = torch.from_numpy(inside).view(1, H, W)
    assert not rot.sim_valid_i[inside].any() and rot.sim_valid_j[inside].all()


def test_photometric_range_determinism_and_switches():
    imgs = torch.rand(2, 3, H, W)
    cfg = AugmentConfig(p_color=1, p_blur=1, p_noise=1, noise_std=0.05)
    a = photometric(imgs, np.random.default_rng(5), cfg)
    b = photometric(imgs, np.random.default_rng(5), cfg)
    c = photometric(imgs, np.random.default_rng(6), cfg)
    assert a.shape == imgs.shape and a.min() >= 0 and a.max() <= 1
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert (a - imgs).abs().mean() > 1e-3
    off = AugmentConfig(p_color=0, p_blur=0, p_noise=0)
    assert torch.equal(photometric(imgs, np.random.default_rng(5), off), imgs)
    assert torch.equal(photometric(imgs, np.random.default_rng(5), AugmentConfig(enabled=False)), imgs)
    # Colour shift alone is the same for both images of the pair: equal inputs stay equal.
    same = torch.rand(1, 3, H, W).expand(2, 3, H, W).clone()
    out = photometric(same, np.random.default_rng(1), AugmentConfig(p_color=1, p_blur=1, p_noise=0))
    assert torch.equal(out[0], out[1]) and not torch.equal(out[0], same[0])


def test_sample_geometric_probabilities():
    rng = np.random.default_rng(0)
    assert np.allclose(sample_geometric(rng, AugmentConfig(p_flip=0, p_rotate=0), K, W).A, np.eye(3))
    f = sample_geometric(rng, AugmentConfig(p_flip=1, p_rotate=0), K, W)
    np.testing.assert_allclose(f.A, flip_transform(K, W).A)
    r = sample_geometric(rng, AugmentConfig(p_flip=0, p_rotate=1, max_rotation_deg=10), K, W)
    angle = math.degrees(math.atan2(r.M[1, 0], r.M[0, 0]))
    assert 0 < abs(angle) <= 10
    assert np.allclose(sample_geometric(rng, AugmentConfig(enabled=False, p_flip=1), K, W).A, np.eye(3))
    flips = [sample_geometric(rng, AugmentConfig(p_flip=0.5, p_rotate=0), K, W).A[0, 0] < 0 for _ in range(200)]
    assert 60 < sum(flips) < 140


def test_augment_pair_moves_everything_consistently():
    """Random augmentation: flow still agrees with the depth implied by (K', pose') at the points."""
    rng = np.random.default_rng(2)
    X = rng.uniform([-4, -3, 8], [4, 3, 14], (300, 3))
    cfg = AugmentConfig(p_flip=0.5, p_rotate=1.0, max_rotation_deg=15)
    for seed in range(4):
        out = augment_pair(sample_from_points(X), np.random.default_rng(seed), cfg)
        # Re-derive j's pixels from i's (uv, z), the augmented K and pose: they must match uv_j.
        Xi = np.linalg.inv(out.K) @ np.vstack([out.uv_i.T, np.ones(len(X))]) * out.z_i
        Xj = out.cam_j_from_cam_i[:3, :3] @ Xi + out.cam_j_from_cam_i[:3, 3:]
        np.testing.assert_allclose(proj(Xj.T, out.K), out.uv_j, atol=1e-8)
        np.testing.assert_allclose(Xj[2], out.z_j, rtol=1e-10)


def test_config_validation():
    with pytest.raises(InputError, match="p_flp"):
        AugmentConfig.from_dict({"p_flp": 0.5})
    with pytest.raises(InputError, match="p_blur"):
        AugmentConfig.from_dict({"p_blur": 1.5})
    with pytest.raises(InputError, match="blur_sigma"):
        AugmentConfig.from_dict({"blur_sigma": [1.0, 0.5]})
    cfg = AugmentConfig.from_dict({"p_flip": 0.25, "blur_sigma": [0.1, 0.5]})
    assert cfg.p_flip == 0.25 and cfg.blur_sigma == (0.1, 0.5)

"""Adaptive and plain TSDF fusion on analytic scenes (tiny images, few frames)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

from endorecon.fusion import (
    AdaptiveTSDF,
    PlainTSDF,
    averaging_rate,
    build_fusion,
    drop_seen_through,
    free_space_counts,
    seen_through_fraction,
    fuse_frames,
    read_mesh_ply,
    truncation,
)
from endorecon.fusion.tsdf import _torch_view
from endorecon.utils.errors import InputError

H, W = 64, 80
K = np.array([[70.0, 0.0, 40.0], [0.0, 70.0, 31.0], [0.0, 0.0, 1.0]])  # pixel-centre convention


def look_at(center, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """cam_from_world of a camera at ``center`` looking at ``target`` (x right, y down, z forward)."""
    c = np.asarray(center, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ c
    return T


def rays_cam() -> np.ndarray:
    """(H, W, 3) camera-frame ray directions with z = 1 (pixel centres)."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)


def plane_depth(T: np.ndarray, n, d) -> np.ndarray:
    """z-depth of the plane {x: n.x = d} seen by camera ``T`` (cam_from_world); 0 where missed."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    R, t = T[:3, :3], T[:3, 3]
    C = -R.T @ t
    dirs = rays_cam() @ R  # world directions (rows: R^T dir)
    z = (d - n @ C) / (dirs @ n)
    return np.where(z > 0, z, 0.0)


def sphere_depth_inside(T: np.ndarray, radius: float) -> np.ndarray:
    """z-depth of a sphere of ``radius`` centred at the origin, seen from a camera inside it."""
    R, t = T[:3, :3], T[:3, 3]
    C = -R.T @ t
    dirs = rays_cam() @ R
    a = (dirs * dirs).sum(-1)
    b = 2 * dirs @ C
    c = C @ C - radius**2
    return (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)  # far root: the wall in front of the camera


def saved_per_setting(cls, voxel, depths, stds, poses, tmp_path, key, values):
    """Fuse the frames once per value of the volume setting ``key``: the saved and the extracted meshes' vertices
    per value, and the last volume."""
    kw = {"compile": False} if cls is AdaptiveTSDF else {}
    saved, extracted = {}, {}
    for value in values:
        vol = cls(voxel, **{key: value}, **kw)
        integrate_all(vol, depths, stds, poses)
        saved[value] = read_mesh_ply(vol.save_mesh(tmp_path / f"mesh_{key}_{value}.ply")).vertex.positions.numpy()
        extracted[value] = vol.extract_mesh().vertex.positions.numpy()
    return saved, extracted, vol


def integrate_all(vol, depths, stds, poses, colors=None, masks=None):
    for i, (d, s, T) in enumerate(zip(depths, stds, poses)):
        col = np.full((H, W, 3), 0.5, np.float32) if colors is None else colors[i]
        vol.integrate(d.astype(np.float32), s.astype(np.float32), col, K, T, None if masks is None else masks[i])


# ---------------------------------------------------------------- kernel maths
def test_averaging_rate_analytic_and_bounds():
    S = torch.tensor([1.0, 1.0, 1.0, 0.0, 5.0, 1e-6])
    Sig = torch.tensor([1.0, 0.1, 10.0, 1.0, 1e-6, 5.0])
    r = averaging_rate(S, Sig, 0.1, 0.8)
    assert r[0] == pytest.approx(0.5)  # equal stds -> 1/2
    assert r[1] == pytest.approx(0.8)  # confident new observation: capped at C2
    assert r[2] == pytest.approx(0.1)  # uncertain new observation: floored at C1
    g = torch.Generator().manual_seed(0)
    S, Sig = torch.rand(1000, generator=g) * 3, torch.rand(1000, generator=g) * 3 + 1e-4
    r = averaging_rate(S, Sig, 0.1, 0.8)
    assert r.min() >= 0.1 and r.max() <= 0.8
    inside = (r > 0.1) & (r < 0.8)
    assert torch.allclose(r[inside], (S**2 / (S**2 + Sig**2))[inside])


def test_truncation_floor_and_cap():
    t = truncation(torch.tensor([0.0, 0.1, 1.0, 100.0]), 3.0, 0.6, 6.0)
    assert torch.allclose(t, torch.tensor([0.6, 0.6, 3.0, 6.0]))


# ---------------------------------------------------------------- accuracy
@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_noisy_tilted_plane_within_half_voxel(cls):
    voxel = 0.02
    n, d = np.array([0.2, -0.1, 1.0]), 1.0
    n_unit = n / np.linalg.norm(n)
    rng = np.random.default_rng(1)
    poses = [look_at((0.1 * np.cos(a), 0.1 * np.sin(a), 0.0), (0.0, 0.0, 1.0)) for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    sigma = 0.3 * voxel
    depths = []
    for T in poses:
        z = plane_depth(T, n, d)
        depths.append(z + sigma * rng.standard_normal(z.shape))
    stds = [np.full((H, W), sigma) for _ in poses]
    vol = cls(voxel, **({"compile": False} if cls is AdaptiveTSDF else {}))
    integrate_all(vol, depths, stds, poses)
    mesh = vol.extract_mesh()
    p = mesh.vertex.positions.numpy()
    assert len(p) > 500
    dist = np.abs(p @ n_unit - d)  # plane_depth renders {x: n_unit . x = d}
    assert np.mean(dist) < 0.5 * voxel, np.mean(dist) / voxel
    assert np.median(dist) < 0.5 * voxel


def test_noisy_sphere_from_inside_within_half_voxel():
    voxel, radius = 0.02, 1.0
    rng = np.random.default_rng(2)
    poses = [look_at((0.1 * np.cos(a), 0.05 * np.sin(a), -0.2), (0.2 * np.cos(a), 0.0, 1.0)) for a in np.linspace(0, 2 * np.pi, 5, endpoint=False)]
    depths, stds = [], []
    for T in poses:
        z = sphere_depth_inside(T, radius)
        s = 0.2 * voxel * (1 + rng.random(z.shape))  # per-pixel std in [0.2, 0.4] voxels
        depths.append(z + s * rng.standard_normal(z.shape))
        stds.append(s)
    vol = AdaptiveTSDF(voxel, compile=False)
    integrate_all(vol, depths, stds, poses)
    p = vol.extract_mesh().vertex.positions.numpy()
    assert len(p) > 500
    dist = np.abs(np.linalg.norm(p, axis=1) - radius)
    assert np.mean(dist) < 0.5 * voxel and np.median(dist) < 0.5 * voxel


# ---------------------------------------------------------------- update rule
def _voxel_value(vol: AdaptiveTSDF, xyz, name="tsdf") -> float:
    """Value of the voxel at the grid point ``xyz`` (world), read from the hash map."""
    r = vol.block_resolution
    g = np.rint(np.asarray(xyz) / vol.voxel_size).astype(np.int64)
    blk = np.floor_divide(g, r)
    loc = g - blk * r
    buf, found = vol.vbg.hashmap().find(o3d.core.Tensor(blk[None].astype(np.int32)))
    assert bool(found.numpy()[0])
    a = _torch_view(vol.vbg.attribute(name))
    return float(a[int(buf.numpy()[0]), loc[2], loc[1], loc[0]].reshape(-1)[0])


@pytest.mark.parametrize("std_mode", ["propagate", "average"])
def test_exponential_update_matches_formula_and_rate_bounds(std_mode):
    voxel = 0.02
    vol = AdaptiveTSDF(voxel, c1=0.1, c2=0.8, trunc_std_multiplier=3.0, trunc_min_voxels=4.0, std_mode=std_mode, compile=False)
    T = np.eye(4)
    zvox = 1.0  # voxel at (0, 0, 1): projects onto pixel (40, 31) exactly
    d1, s1 = 1.03, 0.01  # trunc1 = max(0.03, 0.08) = 0.08
    d2, s2 = 0.98, 0.02  # trunc2 = max(0.06, 0.08) = 0.08
    vol.integrate(np.full((H, W), d1, np.float32), np.full((H, W), s1, np.float32), np.full((H, W, 3), 0.2, np.float32), K, T, return_rate=True)
    r1 = vol.last_rate
    assert torch.all((r1 == 0) | (r1 == 1))  # first frame: fresh voxels take the observation as is
    obs1 = (d1 - zvox) / 0.08
    assert _voxel_value(vol, (0, 0, zvox)) == pytest.approx(obs1, abs=1e-5)
    assert _voxel_value(vol, (0, 0, zvox), "std") == pytest.approx(s1, abs=1e-7)
    vol.integrate(np.full((H, W), d2, np.float32), np.full((H, W), s2, np.float32), np.full((H, W, 3), 0.6, np.float32), K, T, return_rate=True)
    r2 = vol.last_rate
    updated_old = (r2 > 0) & (r2 < 1)
    assert bool(updated_old.any())
    assert r2[updated_old].min() >= 0.1 - 1e-6 and r2[updated_old].max() <= 0.8 + 1e-6
    r = s1**2 / (s1**2 + s2**2)  # 0.2, inside [C1, C2]
    obs2 = (d2 - zvox) / 0.08
    assert _voxel_value(vol, (0, 0, zvox)) == pytest.approx((1 - r) * obs1 + r * obs2, abs=1e-5)
    if std_mode == "average":
        expected_std = (1 - r) * s1 + r * s2
    else:  # unclamped r: inverse-variance fusion of the two stds
        expected_std = (s1**2 * s2**2 / (s1**2 + s2**2)) ** 0.5
        assert expected_std == pytest.approx(((1 - r) ** 2 * s1**2 + r**2 * s2**2) ** 0.5)
    assert _voxel_value(vol, (0, 0, zvox), "std") == pytest.approx(expected_std, abs=1e-6)
    assert _voxel_value(vol, (0, 0, zvox), "weight") == 2


def test_large_std_frame_changes_volume_less():
    voxel = 0.02
    T = np.eye(4)
    changes = {}
    for s2 in (0.005, 0.05):
        vol = AdaptiveTSDF(voxel, trunc_min_voxels=4.0, compile=False)
        vol.integrate(np.full((H, W), 1.007, np.float32), np.full((H, W), 0.005, np.float32), None, K, T)
        before = _torch_view(vol.vbg.attribute("tsdf")).clone()
        seen = _torch_view(vol.vbg.attribute("weight")) > 0
        vol.integrate(np.full((H, W), 1.047, np.float32), np.full((H, W), s2, np.float32), None, K, T)
        after = _torch_view(vol.vbg.attribute("tsdf"))[: before.shape[0]]
        changes[s2] = float((after - before)[seen].abs().sum())
    assert changes[0.05] < 0.5 * changes[0.005]


@pytest.mark.parametrize("std_mode", ["propagate", "average"])
def test_colours_converge_to_observed_colour(std_mode):
    voxel, n = 0.02, 30
    poses = [look_at((0.05 * np.cos(a), 0.05 * np.sin(a), 0.0), (0.0, 0.0, 1.0)) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    depths = [plane_depth(T, (0, 0, 1.0), 1.007) for T in poses]
    stds = [np.full((H, W), 0.005) for _ in poses]
    red, blue = np.array([0.9, 0.1, 0.1], np.float32), np.array([0.2, 0.4, 0.7], np.float32)
    colors = [np.broadcast_to(red if i == 0 else blue, (H, W, 3)).copy() for i in range(n)]
    vol = AdaptiveTSDF(voxel, std_mode=std_mode, compile=False)
    errors = []
    for i in range(n):
        integrate_all(vol, depths[i : i + 1], stds[i : i + 1], poses[i : i + 1], colors[i : i + 1])
        if i in (1, 5, n - 1):
            mesh = vol.extract_mesh()
            p, c = mesh.vertex.positions.numpy(), mesh.vertex.colors.numpy()
            central = (np.abs(p[:, 0]) < 0.15) & (np.abs(p[:, 1]) < 0.15)
            errors.append(np.abs(c[central] - blue).max())
    # the first (red) frame fades: the rate never drops below C1 = 0.1, so its share is <= 0.9^(n - 10) / 10 at the end
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.02


# ---------------------------------------------------------------- invalid pixels
@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_nan_inf_and_masked_pixels_are_ignored(cls):
    voxel = 0.02
    T = np.eye(4)
    d = np.full((H, W), 1.007, np.float32)
    d[:, W // 2 :] = np.nan
    d[: H // 4, : W // 2] = np.inf
    mask = np.ones((H, W), bool)
    mask[H // 2 :, : W // 2] = False
    d[H // 2 :, : W // 2] = 0.3  # bogus depth under the mask
    vol = cls(voxel, **({"compile": False} if cls is AdaptiveTSDF else {}))
    vol.integrate(d, np.full((H, W), 0.005, np.float32), np.full((H, W, 3), 0.5, np.float32), K, T, mask)
    for name in ("tsdf", "weight", "color"):
        assert torch.isfinite(_torch_view(vol.vbg.attribute(name))).all()
    p = vol.extract_mesh().vertex.positions.numpy()
    assert len(p) > 50
    u = p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]
    v = p[:, 1] / p[:, 2] * K[1, 1] + K[1, 2]
    assert np.all(np.abs(p[:, 2] - 1.007) < 0.5 * voxel)  # nothing at the bogus 0.3
    assert u.max() < W // 2 + 1.5 and v.min() > H // 4 - 1.5 and v.max() < H // 2 + 1.5
    # an all-invalid frame changes nothing
    before = _torch_view(vol.vbg.attribute("tsdf")).clone()
    vol.integrate(np.full((H, W), np.nan, np.float32), np.full((H, W), 0.005, np.float32), None, K, T)
    assert torch.equal(_torch_view(vol.vbg.attribute("tsdf"))[: before.shape[0]], before)


def test_bad_std_pixels_are_ignored():
    vol = AdaptiveTSDF(0.02, compile=False)
    s = np.full((H, W), 0.005, np.float32)
    s[:, W // 2 :] = np.nan
    s[:, : W // 4] = 0.0
    vol.integrate(np.full((H, W), 1.007, np.float32), s, None, K, np.eye(4))
    p = vol.extract_mesh().vertex.positions.numpy()
    u = p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]
    assert len(p) > 0 and u.min() > W // 4 - 1.5 and u.max() < W // 2 + 1.5


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "change",
    [
        {"depth": np.ones((H, W, 3), np.float32)},
        {"std": np.ones((H, W + 1), np.float32)},
        {"std": None},
        {"color": np.ones((H, W), np.float32)},
        {"K": np.eye(4)},
        {"cam_from_world": np.eye(4)[:3]},
        {"cam_from_world": np.full((4, 4), np.nan)},
        {"mask": np.ones((H - 1, W), bool)},
        {"std": np.ones((W, H), np.float32)},  # as many elements as (H, W): a reshape would scramble it
        {"mask": np.ones((W, H), bool)},
    ],
)
def test_bad_inputs_raise_clear_errors(change):
    args = dict(depth=np.ones((H, W), np.float32), std=np.ones((H, W), np.float32), color=np.zeros((H, W, 3), np.float32),
                K=K, cam_from_world=np.eye(4), mask=None)
    args.update(change)
    with pytest.raises(InputError, match="fusion"):
        AdaptiveTSDF(0.02, compile=False).integrate(**args)


def test_pose_and_intrinsics_that_require_grad_are_accepted():
    vol = AdaptiveTSDF(0.02, compile=False)
    vol.integrate(np.ones((H, W), np.float32), np.full((H, W), 0.01, np.float32), None,
                  torch.tensor(K, requires_grad=True), torch.eye(4, dtype=torch.float64, requires_grad=True))
    assert vol.frames == 1


def test_fuse_frames_names_the_frame_without_depth(tmp_path):
    frame = dict(std=np.ones((H, W), np.float32), color=np.zeros((H, W, 3), np.float32), K=K, cam_from_world=np.eye(4))
    with pytest.raises(InputError, match="frame 0 has no 'depth'"):
        fuse_frames({"name": "adaptive", "voxel_size": 0.02, "compile": False}, [frame], tmp_path / "m.ply")
    frame = dict(frame, depth=np.ones((H, W), np.float32))
    del frame["std"]
    with pytest.raises(InputError, match="frame 0 has no 'std'"):
        fuse_frames({"name": "adaptive", "voxel_size": 0.02, "compile": False}, [frame], tmp_path / "m.ply")
    assert not (tmp_path / "m.ply").exists()


def test_truncated_ply_names_the_file(tmp_path):
    frames = [dict(depth=np.full((H, W), 1.0, np.float32), std=np.full((H, W), 0.01, np.float32),
                   color=np.full((H, W, 3), 0.25, np.float32), K=K, cam_from_world=np.eye(4))]
    out = fuse_frames({"name": "adaptive", "voxel_size": 0.02, "compile": False}, frames, tmp_path / "m.ply")
    data = out.read_bytes()
    cut = tmp_path / "cut.ply"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated") as e:
        read_mesh_ply(cut)
    assert e.value.path == cut


def test_plain_tsdf_fuses_every_pixel_with_its_colour():
    """Open3D's bound check dropped the last column / row and fused column 0 without colour."""
    for line in (np.s_[:, 0], np.s_[:, W - 1], np.s_[0, :], np.s_[H - 1, :]):
        depth = np.zeros((H, W), np.float32)
        depth[line] = 1.0
        vol = PlainTSDF(0.02, block_search="every_pixel")
        vol.integrate(depth, None, np.full((H, W, 3), 0.25, np.float32), K, np.eye(4))
        w = _torch_view(vol.vbg.attribute("weight")).reshape(-1)
        c = _torch_view(vol.vbg.attribute("color")).reshape(-1, 3)
        seen = w > 0
        # a line of 64 or 80 pixels 1.0 away, 6 voxels of truncation each side: hundreds of voxels
        assert int(seen.sum()) > 300, line
        assert torch.allclose(c[seen], torch.full_like(c[seen], 0.25 * 255), atol=0.5), line


def test_a_reused_block_slot_starts_empty():
    """Open3D leaves a freed slot's values in place; a block activated into it must not inherit them."""
    import open3d.core as o3c

    vol = AdaptiveTSDF(0.02, compile=False, block_count=2000)
    hm = vol.vbg.hashmap()
    keys = o3c.Tensor(np.array([[100, 100, 100], [101, 100, 100]], np.int32))
    hm.activate(keys)
    buf, _ = hm.find(keys)
    for name in ("tsdf", "weight", "std", "color"):
        _torch_view(vol.vbg.attribute(name))[_torch_view(buf).long()] = float("nan")
    hm.erase(keys)
    vol.integrate(np.ones((H, W), np.float32), np.full((H, W), 0.005, np.float32), None, K, np.eye(4))
    active = _torch_view(hm.active_buf_indices()).long()
    for name in ("tsdf", "weight", "std", "color"):
        assert torch.isfinite(_torch_view(vol.vbg.attribute(name))[active]).all(), name


def test_bad_config_raises():
    with pytest.raises(InputError, match="unknown fusion.name"):
        build_fusion({"name": "nope", "voxel_size": 0.1}, 1.0)
    with pytest.raises(InputError, match="voxel_size"):
        build_fusion({"name": "adaptive", "voxel_size": None}, None)
    with pytest.raises(InputError, match="c1"):
        build_fusion({"name": "adaptive", "voxel_size": 0.1, "c1": 0.9, "c2": 0.5}, 1.0)


def test_build_fusion_from_config_files():
    from omegaconf import OmegaConf

    cfg = OmegaConf.load("conf/fusion/adaptive.yaml")
    vol = build_fusion(cfg, median_depth=20.0)
    assert isinstance(vol, AdaptiveTSDF)
    assert vol.voxel_size == pytest.approx(cfg.voxel_fraction * 20.0)
    assert (vol.c1, vol.c2) == (0.1, 0.8)
    assert vol.depth_max == pytest.approx(cfg.depth_max_factor * 20.0)
    plain = build_fusion(OmegaConf.load("conf/fusion/plain.yaml"), median_depth=20.0)
    assert isinstance(plain, PlainTSDF)


# ---------------------------------------------------------------- outputs
def test_fuse_frames_writes_ply_with_std_and_skips_existing(tmp_path):
    T = np.eye(4)
    frames = [dict(depth=np.full((H, W), 1.007, np.float32), std=np.full((H, W), 0.01, np.float32),
                   color=np.full((H, W, 3), 0.25, np.float32), K=K, cam_from_world=T, mask=None) for _ in range(2)]
    cfg = {"name": "adaptive", "voxel_size": None, "voxel_fraction": 0.02, "compile": False, "device": "auto"}
    out = fuse_frames(cfg, frames, tmp_path / "mesh.ply")
    mesh = read_mesh_ply(out)
    std = mesh.vertex["std"].numpy()
    assert len(std) > 100 and np.allclose(std, 0.01 / np.sqrt(2), atol=1e-6)  # two equal observations, std_mode propagate
    assert np.allclose(mesh.vertex.colors.numpy(), 0.25, atol=1 / 255)
    assert np.abs(mesh.vertex.positions.numpy()[:, 2] - 1.007).max() < 0.01
    other = o3d.t.io.read_triangle_mesh(str(out))  # a standard PLY reader gets geometry and colours
    assert other.vertex.positions.shape[0] == len(std)
    assert list(tmp_path.iterdir()) == [out]  # no temp files left
    mtime = out.stat().st_mtime_ns
    assert fuse_frames(cfg, iter([]), out) == out and out.stat().st_mtime_ns == mtime


def test_compile_failure_falls_back_to_eager():
    vol = AdaptiveTSDF(0.02, compile=True)

    def broken(*a, **k):
        raise RuntimeError("no compiler")

    vol._update.impl = broken  # stands in for a compiled function whose compilation fails
    vol._clean.impl = vol._clean.fn
    with pytest.warns(UserWarning, match="eager"):
        vol.integrate(np.full((H, W), 1.007, np.float32), np.full((H, W), 0.01, np.float32), None, K, np.eye(4))
    assert vol.compile_seconds is not None
    assert len(vol.extract_mesh().vertex.positions) > 0


@pytest.mark.slow
def test_compiled_kernel_matches_eager():
    rng = np.random.default_rng(3)
    poses = [look_at((0.05 * i, 0.0, 0.0), (0.0, 0.0, 1.0)) for i in range(3)]
    depths = [plane_depth(T, (0.1, 0, 1.0), 1.0) + 0.005 * rng.standard_normal((H, W)) for T in poses]
    stds = [0.005 * (1 + rng.random((H, W))) for _ in poses]
    vols = [AdaptiveTSDF(0.02, compile=c) for c in (False, True)]
    import warnings

    with warnings.catch_warnings():
        # an eager fallback (it warns) would compare eager with eager
        warnings.filterwarnings("error", message=r"torch\.compile (unavailable|of .* failed)")
        for v in vols:
            integrate_all(v, depths, stds, poses)
    assert vols[1].compile_seconds is not None
    assert vols[1]._update.impl is not vols[1]._update.fn and vols[1]._clean.impl is not vols[1]._clean.fn
    a, b = (_voxels_by_key(v) for v in vols)
    assert torch.equal(a["keys"], b["keys"])
    # floor(u + 0.5) may flip for a voxel projecting onto a pixel border (fused multiply-add), so compare the bulk
    for name in ("tsdf", "std", "color", "weight"):
        diff = (a[name] - b[name]).abs()
        assert (diff > 1e-4).float().mean() < 1e-3, name


def _voxels_by_key(vol: AdaptiveTSDF) -> dict[str, torch.Tensor]:
    hm = vol.vbg.hashmap()
    buf = _torch_view(hm.active_buf_indices()).long()
    keys = _torch_view(hm.key_tensor())[buf].long()
    order = torch.argsort((keys[:, 0] * 100003 + keys[:, 1]) * 100003 + keys[:, 2])
    out = {"keys": keys[order]}
    for name in ("tsdf", "std", "color", "weight"):
        a = _torch_view(vol.vbg.attribute(name))
        out[name] = a.reshape(a.shape[0], -1)[buf[order]]
    return out


# ------------------------------------------------------------ mesh cleaning
@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_small_floating_pieces_are_dropped(cls):
    """A patch of outlier depth from one frame makes a separate small piece; min_component_fraction removes it
    and leaves the plane whole."""
    voxel = 0.02
    poses = [look_at((0.05 * np.cos(a), 0.05 * np.sin(a), 0.0), (0.0, 0.0, 1.0)) for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    depths = [plane_depth(T, (0.0, 0.0, 1.0), 1.0) for T in poses]
    outlier = depths[0].copy()
    outlier[20:30, 30:40] = 0.6  # 0.4 in front of the plane: far outside every truncation band
    depths[0] = outlier
    stds = [np.full((H, W), 0.2 * voxel) for _ in poses]
    kw = {"compile": False} if cls is AdaptiveTSDF else {}

    def fused(fraction):
        vol = cls(voxel, min_component_fraction=fraction, **kw)
        integrate_all(vol, depths, stds, poses)
        return vol.extract_mesh().vertex.positions.numpy()

    kept, cleaned = fused(0.0), fused(0.05)
    assert (np.abs(kept[:, 2] - 0.6) < 0.1).sum() > 10  # the outlier piece is there without cleaning
    assert (np.abs(cleaned[:, 2] - 0.6) < 0.1).sum() == 0
    plane = np.abs(kept[:, 2] - 1.0) < 0.1
    assert (np.abs(cleaned[:, 2] - 1.0) < 0.1).sum() == plane.sum()
    with pytest.raises(InputError, match="min_component_fraction"):
        cls(voxel, min_component_fraction=1.5, **kw)


def _grid_mesh(n: int) -> o3d.t.geometry.TriangleMesh:
    """An n x n vertex grid in the z = 0 plane, two triangles per cell."""
    v = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    verts = np.concatenate([v, np.zeros((len(v), 1))], 1).astype(np.float32)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)]).astype(np.int64)
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(verts)
    mesh.triangle.indices = o3d.core.Tensor(faces)
    return mesh


def test_trim_boundary_removes_rings_of_an_open_grid_and_nothing_of_a_closed_mesh():
    from endorecon.fusion import trim_boundary

    n = 10
    grid = _grid_mesh(n)
    for rings in (1, 2, 3):
        out = trim_boundary(grid, rings)
        pos = out.vertex.positions.numpy()
        # k rings off an n x n grid leave the (n - 2k) x (n - 2k) vertex grid inside
        assert len(pos) == (n - 2 * rings) ** 2
        assert pos[:, :2].min() == rings and pos[:, :2].max() == n - 1 - rings
        assert len(out.triangle.indices) == 2 * (n - 1 - 2 * rings) ** 2
    assert trim_boundary(grid, 0) is grid
    assert len(trim_boundary(grid, 6).triangle.indices) == 0  # more rings than the grid has: nothing left
    sphere = o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh.create_sphere(1.0, 10))
    assert len(trim_boundary(sphere, 2).triangle.indices) == len(sphere.triangle.indices)
    with pytest.raises(InputError, match="boundary_trim_rings"):
        trim_boundary(grid, -1)


@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_saved_mesh_is_trimmed_and_says_so_extracted_mesh_is_not(cls, tmp_path):
    from endorecon.fusion import boundary_trim_rings_of

    voxel = 0.02
    poses = [look_at((0.05 * np.cos(a), 0.05 * np.sin(a), 0.0), (0.0, 0.0, 1.0)) for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    depths = [plane_depth(T, (0.0, 0.0, 1.0), 1.0) for T in poses]
    stds = [np.full((H, W), 0.2 * voxel) for _ in poses]
    kw = {"compile": False} if cls is AdaptiveTSDF else {}
    counts = {}
    for rings in (0, 1):
        vol = cls(voxel, boundary_trim_rings=rings, **kw)
        integrate_all(vol, depths, stds, poses)
        path = vol.save_mesh(tmp_path / f"mesh{rings}.ply")
        assert boundary_trim_rings_of(path) == rings
        counts[rings] = (len(read_mesh_ply(path).triangle.indices), len(vol.extract_mesh().triangle.indices))
    assert counts[0][0] == counts[0][1] == counts[1][1]  # extraction (simulated depth) keeps the boundary
    assert 0 < counts[1][0] < counts[0][0]
    with pytest.raises(InputError, match="boundary_trim_rings"):
        cls(voxel, boundary_trim_rings=-1, **kw)


# ---------------------------------------------------------------- block activation
def test_pixel_band_blocks_cover_the_band_at_every_pixel():
    from endorecon.fusion import pixel_band_blocks

    T = look_at((0.1, -0.05, -0.3), (0.0, 0.0, 1.0))
    d = plane_depth(T, (0.2, 0.1, -1.0), -1.0).astype(np.float32)
    d[::3, ::2] = 0.0  # unusable pixels are not walked
    trunc, block = 0.06, 0.08
    got = pixel_band_blocks(torch.from_numpy(d), torch.from_numpy(K), torch.from_numpy(T), trunc, block).numpy()
    assert got.dtype == np.int32 and len(np.unique(got, axis=0)) == len(got)
    # brute force: every usable pixel's band sampled 40x finer
    v, u = np.nonzero(d > 0)
    rays = rays_cam()[v, u]
    zs = d[v, u, None] + np.linspace(-trunc, trunc, 161)[None]
    p_cam = rays[:, None, :] * zs[..., None]
    p_world = (p_cam - T[:3, 3]) @ T[:3, :3]
    ref = np.unique(np.floor(p_world.reshape(-1, 3) / block).astype(np.int32), axis=0)
    got_set, ref_set = set(map(tuple, got)), set(map(tuple, ref))
    assert got_set <= ref_set  # nothing outside the band
    assert len(got_set) >= 0.98 * len(ref_set)  # a coarser walk may only miss blocks it clips at a corner
    surface = np.unique(np.floor(((rays * d[v, u, None]) - T[:3, 3]) @ T[:3, :3] / block).astype(np.int32), axis=0)
    assert set(map(tuple, surface)) <= got_set  # every observed surface point's block is there
    assert len(pixel_band_blocks(torch.zeros(H, W), torch.from_numpy(K), torch.from_numpy(T), trunc, block)) == 0


@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_frame_with_few_usable_pixels_is_fused(cls):
    # Open3D's block search looks at every 4th pixel: a frame whose usable pixels all lie between them
    # (what is left of a frame after depth_max) made it raise "No block is touched" and stopped training.
    voxel = 0.02
    T = np.eye(4)
    d = np.zeros((H, W), np.float32)
    d[21:23, 33:35] = 1.0
    vol = cls(voxel, **({"compile": False} if cls is AdaptiveTSDF else {}))
    img = o3d.t.geometry.Image(o3d.core.Tensor(d))
    Kc = o3d.core.Tensor(vol._corner_K(K))
    with pytest.raises(RuntimeError, match="No block is touched"):  # the case the fallback is for
        vol.vbg.compute_unique_block_coordinates(img, Kc, o3d.core.Tensor(T), 1.0, 1e30, 6.0)
    vol.integrate(d, np.full((H, W), 0.005, np.float32), None, K, T)
    assert vol.vbg.hashmap().size() > 0
    w = _torch_view(vol.vbg.attribute("weight"))
    assert (w > 0).sum() > 0


# ---------------------------------------------------------------- mask edge
def _near_invalid_brute(mask: np.ndarray, r: float) -> np.ndarray:
    """Valid pixels within Euclidean distance r of an invalid pixel or of a pixel outside the image."""
    h, w = mask.shape
    pad = int(np.ceil(r)) + 1
    big = np.zeros((h + 2 * pad, w + 2 * pad), bool)
    big[pad:pad + h, pad:pad + w] = mask
    iv, iu = np.nonzero(~big)
    v, u = np.nonzero(mask)
    d2 = (v[:, None] + pad - iv[None]) ** 2 + (u[:, None] + pad - iu[None]) ** 2
    out = np.zeros_like(mask)
    out[v, u] = d2.min(1) <= r * r
    return out


def test_erode_mask_matches_brute_force_and_analytic_cases():
    from endorecon.fusion.kernel import erode_mask

    full = torch.ones(7, 7, dtype=torch.bool)
    assert erode_mask(full, 0) is full
    e1 = erode_mask(full, 1).numpy()
    assert e1[1:6, 1:6].all() and e1.sum() == 25  # the image border counts as invalid
    one_hole = torch.ones(11, 11, dtype=torch.bool)
    one_hole[5, 5] = False
    e2 = erode_mask(one_hole, 2).numpy()
    assert not e2[5, 7] and not e2[6, 6] and e2[6, 7]  # distance 2 and sqrt(2) go, sqrt(5) stays
    v, u = np.mgrid[0:H, 0:W]
    mask = ((u - 40) ** 2 + (v - 31.5) ** 2 <= 27**2) & ~((u - 50) ** 2 + (v - 20) ** 2 <= 9)
    for r in (1, 2, 3):
        got = erode_mask(torch.from_numpy(mask), r).numpy()
        np.testing.assert_array_equal(got, mask & ~_near_invalid_brute(mask, r))
    with pytest.raises(ValueError):
        erode_mask(full, -1)
    with pytest.raises(InputError, match="mask_erode_px"):
        AdaptiveTSDF(0.02, mask_erode_px=-1)
    with pytest.raises(InputError, match="mask_erode_px"):
        PlainTSDF(0.02, mask_erode_px=1.5)


@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_depth_at_the_mask_edge_is_not_fused(cls):
    # a plane at z = 1 whose outer 2 px ring (inside the mask) reads 30 % too far, as the network's depth
    # does where the dark border bleeds in; with mask_erode_px=2 none of it reaches the mesh
    voxel = 0.02
    v, u = np.mgrid[0:H, 0:W]
    mask = (u - 40) ** 2 + (v - 31.5) ** 2 <= 27**2
    ring = _near_invalid_brute(mask, 2)
    d = np.where(ring, 1.3, 1.0).astype(np.float32)
    kw = {"compile": False} if cls is AdaptiveTSDF else {}
    z = {}
    for r in (0, 2):
        vol = cls(voxel, mask_erode_px=r, **kw)
        vol.integrate(d, np.full((H, W), 0.005, np.float32), None, K, np.eye(4), mask)
        z[r] = vol.extract_mesh().vertex.positions.numpy()[:, 2]
    assert len(z[2]) > 100
    assert np.abs(z[2] - 1.0).max() < 0.5 * voxel
    assert np.abs(z[0] - 1.0).max() > 2 * voxel  # without erosion the biased ring bends the mesh's edge
    # no mask: the image border is eroded instead
    vol = cls(voxel, mask_erode_px=2, **kw)
    vol.integrate(np.ones((H, W), np.float32), np.full((H, W), 0.005, np.float32), None, K, np.eye(4))
    p = vol.extract_mesh().vertex.positions.numpy()
    u_p = p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]
    assert u_p.min() > 2 - 0.5 - 1.0 and u_p.max() < W - 3 + 0.5 + 1.0  # fused pixels are 2..W-3 (+- a voxel)


def _band_voxels_missed(vol, d, T, trunc):
    """(voxels within 0.9 trunc of a usable pixel's depth, along z, and in view; how many have weight 0)."""
    from endorecon.fusion import pixel_band_blocks

    r = vol.block_resolution
    blocks = pixel_band_blocks(torch.from_numpy(d), torch.from_numpy(K), torch.from_numpy(T), trunc,
                               vol.voxel_size * r).numpy().astype(np.int64)
    loc = np.stack(np.meshgrid(np.arange(r), np.arange(r), np.arange(r), indexing="ij"), -1).reshape(-1, 3)
    g = (blocks[:, None, :] * r + loc[None]).reshape(-1, 3)
    pc = (g * vol.voxel_size) @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(K[0, 0] * pc[:, 0] / z + K[0, 2])
        v = np.rint(K[1, 1] * pc[:, 1] / z + K[1, 2])
    ok = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    dd = np.zeros_like(z)
    dd[ok] = d[v[ok].astype(int), u[ok].astype(int)]
    g = g[ok & (dd > 0) & (np.abs(dd - z) < 0.9 * trunc)]
    blk = np.floor_divide(g, r)
    loc = g - blk * r
    buf, found = vol.vbg.hashmap().find(o3d.core.Tensor(blk.astype(np.int32)))
    buf, found = buf.numpy().astype(np.int64), found.numpy().astype(bool)
    w = np.zeros(len(g))
    wv = _torch_view(vol.vbg.attribute("weight"))
    w[found] = wv[buf[found], loc[found, 2], loc[found, 1], loc[found, 0]].reshape(-1).numpy()
    return len(g), int((w == 0).sum())


def test_every_pixel_block_search_updates_every_band_voxel():
    # Open3D's block search (every 4th pixel) leaves blocks the band crosses between its samples out of the
    # frame: a few % of the band's voxels on a tilted plane (the block patches of the adaptive mesh)
    voxel = 0.02
    T = look_at((0.1, -0.05, -0.3), (0.0, 0.0, 1.0))
    d = plane_depth(T, (0.2, 0.1, -1.0), -1.0).astype(np.float32)
    missed = {}
    for search in ("sampled", "every_pixel"):
        vol = AdaptiveTSDF(voxel, block_search=search, compile=False, trunc_min_voxels=6.0)
        vol.integrate(d, np.full((H, W), 0.005, np.float32), None, K, T)  # 3 sigma < 6 voxels: trunc = 0.12
        missed[search] = _band_voxels_missed(vol, d, T, 6 * voxel)
    n, miss = missed["every_pixel"]
    assert n > 10000 and miss == 0
    assert missed["sampled"][0] == n and missed["sampled"][1] > 0.01 * n
    for cls in (AdaptiveTSDF, PlainTSDF):
        with pytest.raises(InputError, match="block_search"):
            cls(voxel, block_search="open3d")


# ---------------------------------------------------------------- free-space check of the saved mesh
def _translated(x: float) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = -x  # camera centre at (x, 0, 0), looking along +z
    return T


def test_counts_on_a_plane_analytic():
    """Frames see a plane at z = 2: a point in front is seen through, one on it is on, one behind is hidden,
    one outside the image or behind the camera is not seen; masked and invalid pixels say nothing."""
    n = 3
    depth = torch.full((n, H, W), 2.0, dtype=torch.float64)
    T = torch.stack([_translated(x) for x in (0.0, 0.1, -0.1)])
    Kt = torch.as_tensor(K)
    pts = torch.tensor([[0.0, 0.0, 1.0],    # in front of the plane: free space in every frame
                        [0.0, 0.0, 2.0],    # on it
                        [0.0, 0.0, 2.1],    # within tau behind: still on (|2 - 2.1| <= 0.1 * 2.1)
                        [0.0, 0.0, 3.0],    # hidden behind it
                        [50.0, 0.0, 1.0],   # outside every image
                        [0.0, 0.0, -1.0]],  # behind the cameras
                       dtype=torch.float64)
    on, through = free_space_counts(pts, depth, Kt, T, tau=0.1)
    assert on.tolist() == [0, 3, 3, 0, 0, 0]
    assert through.tolist() == [3, 0, 0, 0, 0, 0]
    assert seen_through_fraction(on, through).tolist() == [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    # tau decides "on": 2.1 is not on the plane within 2 %
    on2, _ = free_space_counts(pts[2:3], depth, Kt, T, tau=0.02)
    assert on2.tolist() == [0]
    # the pixel the first point falls on in frame 0: masked there, NaN in frame 1 -> only frame 2 counts
    u, v = K[0, 2], K[1, 2]  # the point (0, 0, 1) projects to the principal point in frame 0
    mask = torch.ones(n, H, W, dtype=torch.bool)
    mask[0, int(round(v)), int(round(u))] = False
    depth2 = depth.clone()
    uv1 = K[0, 0] * (0.0 - 0.1) / 1.0 + K[0, 2]
    depth2[1, int(round(v)), int(round(uv1))] = float("nan")
    on3, through3 = free_space_counts(pts[:1], depth2, Kt, T, mask, tau=0.1)
    assert (on3.tolist(), through3.tolist()) == ([0], [1])
    # per-frame intrinsics give the same counts as shared ones
    on4, through4 = free_space_counts(pts, depth, Kt.expand(n, 3, 3), T, tau=0.1)
    assert torch.equal(on4, on) and torch.equal(through4, through)


@pytest.mark.parametrize("bad", [dict(points=torch.zeros(4, 2)), dict(depth=torch.ones(H, W)),
                                 dict(cam_from_world=torch.eye(4)[None].repeat(2, 1, 1)), dict(K=torch.eye(2)),
                                 dict(mask=torch.ones(3, 3, dtype=torch.bool)), dict(tau=0.0)])
def test_counts_check_their_inputs(bad):
    args = dict(points=torch.zeros(4, 3, dtype=torch.float64), depth=torch.ones(1, H, W), K=torch.as_tensor(K),
                cam_from_world=torch.eye(4, dtype=torch.float64)[None], mask=None, tau=0.1)
    args.update(bad)
    with pytest.raises(InputError, match="surface views"):
        free_space_counts(**args)


def test_drop_seen_through_removes_the_triangles_at_violated_vertices():
    n = 6
    grid = _grid_mesh(n)
    frac = np.zeros(n * n)
    assert drop_seen_through(grid, frac, 0.5) is grid
    frac[2 * n + 2] = 0.8  # an inner vertex: its six triangles go
    out = drop_seen_through(grid, frac, 0.5)
    assert len(out.triangle.indices) == len(grid.triangle.indices) - 6
    assert len(drop_seen_through(grid, frac, 0.8).triangle.indices) == len(grid.triangle.indices)  # not above
    with pytest.raises(InputError, match="vertices"):
        drop_seen_through(grid, frac[:-1], 0.5)


@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_saved_mesh_loses_surface_the_other_frames_see_through(cls, tmp_path):
    """One frame's outlier patch 0.4 in front of a plane is fused (no size rule here); the three other
    frames see the plane through it, so the saved mesh drops it with the check and keeps it without;
    the extracted mesh (simulated depth) keeps it either way, and the plane stays whole."""
    voxel = 0.02
    poses = [look_at((0.05 * np.cos(a), 0.05 * np.sin(a), 0.0), (0.0, 0.0, 1.0)) for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    depths = [plane_depth(T, (0.0, 0.0, 1.0), 1.0) for T in poses]
    depths[0] = depths[0].copy()
    depths[0][20:30, 30:40] = 0.6
    stds = [np.full((H, W), 0.2 * voxel) for _ in poses]
    kw = {"compile": False} if cls is AdaptiveTSDF else {}
    saved, extracted, vol = saved_per_setting(cls, voxel, depths, stds, poses, tmp_path, "free_space_max_fraction", (None, 0.5))
    for check in (None, 0.5):
        assert (np.abs(extracted[check][:, 2] - 0.6) < 0.1).sum() > 10
    assert (np.abs(saved[None][:, 2] - 0.6) < 0.1).sum() > 10
    assert (np.abs(saved[0.5][:, 2] - 0.6) < 0.1).sum() == 0
    assert vol.last_free_space["removed"] > 0 and vol.last_free_space["frames"] == 4
    plane = lambda p: (np.abs(p[:, 2] - 1.0) < 0.1).sum()  # noqa: E731
    assert plane(saved[0.5]) >= 0.97 * plane(saved[None])
    for bad in (dict(free_space_max_fraction=1.5), dict(free_space_max_fraction="x"), dict(free_space_tau=0.0)):
        with pytest.raises(InputError, match="free_space"):
            cls(voxel, **bad, **kw)


def test_a_frame_without_mask_does_not_switch_off_the_others_masks():
    """Three frames whose left half is masked out (and holds far garbage) and one without a mask: the garbage
    must not count as seeing through the plane (it did: one None mask dropped every mask)."""
    vol = AdaptiveTSDF(0.02, compile=False, free_space_max_fraction=0.5)
    plane = np.ones((H, W), np.float32)
    garbage = plane.copy()
    garbage[:, : W // 2] = 50.0
    mask = np.ones((H, W), bool)
    mask[:, : W // 2] = False
    std = np.full((H, W), 0.005, np.float32)
    vol.integrate(plane, std, None, K, np.eye(4), None)
    for _ in range(3):
        vol.integrate(garbage, std, None, K, np.eye(4), mask)
    mesh = vol.extract_mesh()
    vol.drop_free_space(mesh)
    assert vol.last_free_space["removed"] == 0 and vol.last_free_space["triangles"] > 1000


def test_pixels_without_a_usable_std_do_not_carve_free_space():
    """Three frames whose left half has far garbage with a NaN / zero / inf std: fusion leaves those pixels out,
    so they must not count as seeing through the plane either."""
    vol = AdaptiveTSDF(0.02, compile=False, free_space_max_fraction=0.5)
    plane = np.ones((H, W), np.float32)
    garbage = plane.copy()
    garbage[:, : W // 2] = 50.0
    std = np.full((H, W), 0.005, np.float32)
    vol.integrate(plane, std, None, K, np.eye(4))
    for bad in (np.nan, 0.0, np.inf):
        bad_std = std.copy()
        bad_std[:, : W // 2] = bad
        vol.integrate(garbage, bad_std, None, K, np.eye(4))
    mesh = vol.extract_mesh()
    vol.drop_free_space(mesh)
    assert vol.last_free_space["removed"] == 0 and vol.last_free_space["triangles"] > 1000


# ---------------------------------------------------------------- uncertainty trim of the saved mesh
def test_drop_uncertain_removes_the_triangles_of_vertices_over_the_ratio():
    from endorecon.fusion import drop_uncertain

    n = 6
    grid = _grid_mesh(n)
    std = np.ones((n * n, 1), np.float32)
    inner = 2 * n + 3  # an interior vertex: six triangles share it
    std[inner] = 3.0
    grid.vertex["std"] = o3d.core.Tensor(std)
    out, info = drop_uncertain(grid, 2.0)
    assert len(out.triangle.indices) == len(grid.triangle.indices) - 6
    assert info == dict(triangles=len(grid.triangle.indices), removed=6, median_std=1.0, threshold=2.0, ratio=2.0)
    assert len(out.vertex.positions) == n * n - 1 and out.vertex["std"].numpy().max() == 1.0
    kept, info = drop_uncertain(grid, 3.0)  # not above the threshold: kept
    assert kept is grid and info["removed"] == 0
    std[inner] = np.nan  # a vertex without a finite std goes too
    grid.vertex["std"] = o3d.core.Tensor(std)
    assert len(drop_uncertain(grid, 2.0)[0].triangle.indices) == len(grid.triangle.indices) - 6
    # inf as NaN: the vertex goes and has no say in the median (most stds inf: the rest still judged)
    many_inf = np.where(np.arange(n * n)[:, None] % 3 == 0, 1.0, np.inf).astype(np.float32)
    grid.vertex["std"] = o3d.core.Tensor(many_inf)
    _, info = drop_uncertain(grid, 2.0)
    assert info["median_std"] == 1.0 and info["removed"] > 0
    # the threshold is relative: the same mesh in other units loses the same triangles
    grid.vertex["std"] = o3d.core.Tensor(np.where(np.isfinite(std), std, 3.0) * 250.0)
    out, info = drop_uncertain(grid, 2.0)
    assert len(out.triangle.indices) == len(grid.triangle.indices) - 6 and info["median_std"] == 250.0
    assert drop_uncertain(grid, None) == (grid, None)
    # a median std of 0 (no spread to judge by): nothing goes, and the record says so
    grid.vertex["std"] = o3d.core.Tensor(np.zeros((n * n, 1), np.float32))
    kept, info = drop_uncertain(grid, 2.0)
    assert kept is grid and info["removed"] == 0 and info["median_std"] == 0.0
    no_std = _grid_mesh(n)
    assert drop_uncertain(no_std, 2.0) == (no_std, None)  # plain TSDF meshes have no std
    for bad in (1.0, 0.5, -2, float("nan"), "x", True):
        with pytest.raises(InputError, match="max_std_ratio"):
            drop_uncertain(grid, bad)


def test_saved_adaptive_mesh_loses_surface_fused_with_a_large_std(tmp_path):
    """Four frames see a plane; one half of every frame is fused with 5x the std of the other half.  With
    max_std_ratio = 2 the saved mesh keeps the confident half only; the extracted mesh keeps both."""
    from endorecon.fusion import build_fusion

    voxel = 0.02
    poses = [look_at((0.05 * np.cos(a), 0.05 * np.sin(a), 0.0), (0.0, 0.0, 1.0)) for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    depths = [plane_depth(T, (0.0, 0.0, 1.0), 1.0) for T in poses]
    stds = []
    for _ in poses:
        s = np.full((H, W), 0.2 * voxel)
        s[:, : W // 2] *= 5.0
        stds.append(s)
    saved = {}
    for ratio in (None, 2.0):
        vol = AdaptiveTSDF(voxel, compile=False, max_std_ratio=ratio)
        integrate_all(vol, depths, stds, poses)
        saved[ratio] = read_mesh_ply(vol.save_mesh(tmp_path / f"mesh_{ratio}.ply"))
        assert len(vol.extract_mesh().triangle.indices) == len(saved[None].triangle.indices)
    assert vol.last_uncertain["removed"] > 0
    x_all, x_kept = saved[None].vertex.positions.numpy()[:, 0], saved[2.0].vertex.positions.numpy()[:, 0]
    s_all = saved[None].vertex["std"].numpy().ravel()
    assert s_all[x_all < -0.05].mean() > 3 * s_all[x_all > 0.05].mean()  # the camera's left half is x < 0
    assert (x_kept < -0.05).sum() == 0 and (x_kept > 0.05).sum() >= 0.97 * (x_all > 0.05).sum()
    # the config key reaches the adaptive volume; a bad value stops before any fusion
    assert build_fusion({"name": "adaptive", "voxel_size": voxel, "max_std_ratio": 2.0}).max_std_ratio == 2.0
    with pytest.raises(InputError, match="max_std_ratio"):
        build_fusion({"name": "adaptive", "voxel_size": voxel, "max_std_ratio": 0.5})


def test_no_usable_depth_is_an_error_not_an_empty_mesh(tmp_path):
    """Frames whose depth or std fusion cannot use gave an empty mesh.ply, logged as written, which the next
    run then skipped as done; a first frame without valid depth dropped the depth cut-off without a word."""
    cfg = {"name": "adaptive", "voxel_size": 0.02, "compile": False}

    def frame(depth, std):
        return dict(depth=np.full((H, W), depth, np.float32), std=np.full((H, W), std, np.float32),
                    color=np.full((H, W, 3), 0.25, np.float32), K=K, cam_from_world=np.eye(4))

    out = tmp_path / "m.ply"
    with pytest.raises(InputError, match="none of the 2 frames has a finite, positive depth"):
        fuse_frames(cfg, [frame(np.nan, 0.01), frame(0.0, 0.01)], out)
    with pytest.raises(InputError, match="no surface to save") as e:
        fuse_frames(cfg, [frame(1.0, 0.0), frame(1.0, np.nan)], out)  # no usable std anywhere
    assert e.value.path == out and not out.exists() and list(tmp_path.iterdir()) == []
    # the cut-off comes from the first frame with valid depth: 2 x 1.0, so the 3.0 frame is cut, not fused
    fuse_frames({**cfg, "depth_max_factor": 2.0}, [frame(np.nan, 0.01), frame(1.0, 0.01), frame(3.0, 0.01)], out)
    z = read_mesh_ply(out).vertex.positions.numpy()[:, 2]
    assert np.abs(z - 1.0).max() < 0.05
    with pytest.raises(InputError, match="depth_max_factor is set"):
        build_fusion({"name": "adaptive", "voxel_size": 0.1, "depth_max_factor": 2.0}, float("nan"))
    assert build_fusion({"name": "adaptive", "voxel_size": 0.1, "depth_max_factor": None}, None).depth_max == float("inf")

# Tests that a mutation of the code survived before (a review ran single-point mutations of this package):
# each fails under its mutation and passes on the code.
from endorecon.fusion import drop_small_components, pixel_band_blocks  # noqa: E402


def _plane_vol(std, **kw):
    T = np.eye(4)
    d = np.full((H, W), 1.0, np.float32)
    vol = AdaptiveTSDF(0.01, compile=False, **kw)
    vol.integrate(d, np.full((H, W), std, np.float32), None, K, T)
    return vol

def _sample(vol, z):
    return vol.sample_voxels(torch.tensor([[0.0, 0.0, z]]), ("tsdf", "weight"))

def test_band_behind_surface_and_trunc_cap():
    # trunc = clamp(3 * 0.02, 2 vox, 4 vox) = 0.04: the cap, not k sigma
    vol = _plane_vol(0.02, trunc_min_voxels=2.0, trunc_max_voxels=4.0)
    s = _sample(vol, 0.98)
    assert float(s["tsdf"]) == pytest.approx(0.5, abs=1e-4)       # sdf 0.02 / trunc 0.04
    assert torch.isnan(_sample(vol, 1.06)["tsdf"]).all()         # 1.5 trunc behind: never updated

def test_band_width_follows_the_std():
    # trunc = 3 * 0.05 = 0.15 (15 voxels, within [2, 24]); the allocated band must reach 0.12 in front
    vol = _plane_vol(0.05, trunc_min_voxels=2.0, trunc_max_voxels=24.0)
    s = _sample(vol, 0.88)
    assert float(s["tsdf"]) == pytest.approx(0.8, abs=1e-3)

def test_mesh_weight_threshold_two_needs_two_frames():
    vol = _plane_vol(0.005, mesh_weight_threshold=2.0)
    assert vol.extract_mesh().triangle.indices.shape[0] == 0

def test_just_in_front_within_tau_is_on_not_through():
    depth = torch.full((1, H, W), 2.0, dtype=torch.float64)
    on, through = free_space_counts(torch.tensor([[0.0, 0.0, 1.85]], dtype=torch.float64), depth,
                                    torch.as_tensor(K), torch.eye(4, dtype=torch.float64)[None], tau=0.1)
    assert on.tolist() == [1] and through.tolist() == [0]

def test_largest_piece_is_always_kept():
    a, b = _grid_mesh(3), _grid_mesh(3)
    pa = a.vertex.positions.numpy(); pb = pa + np.array([10, 0, 0], np.float32)
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.concatenate([pa, pb]))
    f = a.triangle.indices.numpy()
    m.triangle.indices = o3d.core.Tensor(np.concatenate([f, f + len(pa)]))
    out = drop_small_components(m, 0.9)  # both pieces under 90 %: the largest stays
    assert out.triangle.indices.shape[0] == len(f)

def test_band_walk_with_trunc_over_two_blocks():
    T = np.eye(4)
    d = torch.full((H, W), 1.0, dtype=torch.float64)
    got = pixel_band_blocks(d, torch.from_numpy(K), torch.from_numpy(T), 0.3, 0.08).numpy()
    zs = set(got[:, 2].tolist())
    assert zs == set(range(int(np.floor(0.7 / 0.08)), int(np.floor(1.3 / 0.08)) + 1))

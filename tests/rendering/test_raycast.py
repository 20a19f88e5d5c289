"""Analytic tests of the ray-cast renderer: planes, a cylinder seen along its axis, GT consistency."""

import numpy as np
import pytest

from endorecon.rendering import MeshRenderer, render_depth
from endorecon.utils.errors import InputError

H, W = 48, 64
K = np.array([[40.0, 0, 31.2], [0, 42.0, 23.7], [0, 0, 1]])


def plane_mesh(z, half=1e3):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return v, f


def cylinder_mesh(radius, length, n=1024, rings=2):
    """Open cylinder x^2 + y^2 = r^2, z in [-1, L], closed by a cap at z = L.

    A fine polygon (n = 1024: cos(pi/n) ~ 1 - 5e-6) so it matches the analytic cylinder to 1e-4.
    """
    ang = 2 * np.pi * np.arange(n) / n
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], 1)
    zs = np.linspace(-1.0, length, rings)
    v = np.concatenate([np.c_[ring, np.full(n, z)] for z in zs] + [[[0, 0, length]]])
    i = np.arange(n)
    j = (i + 1) % n
    faces = []
    for k in range(rings - 1):
        a, b = k * n, (k + 1) * n
        faces += [np.stack([a + i, a + j, b + j], 1), np.stack([a + i, b + j, b + i], 1)]
    last = (rings - 1) * n
    faces.append(np.stack([last + i, last + j, np.full(n, len(v) - 1)], 1))
    return v, np.concatenate(faces)


def rays(K, h, w):
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    return (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]


def look_pose(R, centre):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ centre
    return T


def test_plane_frontal_depth_is_constant():
    r = MeshRenderer(plane_mesh(7.5))
    out = r.render(K, np.eye(4), H, W)
    assert out["hit"].all()
    np.testing.assert_allclose(out["depth"], 7.5, rtol=1e-4)
    # normals point along the winding (+z here), points lie on the plane at z-depth
    np.testing.assert_allclose(np.abs(out["normals_world"][..., 2]), 1, atol=1e-6)
    x, y = rays(K, H, W)
    np.testing.assert_allclose(out["points_world"][..., 0], x * 7.5, atol=1e-3)
    np.testing.assert_allclose(out["points_world"][..., 1], y * 7.5, atol=1e-3)


def test_tilted_plane_from_moved_camera_matches_analytic_depth():
    # plane n.x = d in world; camera rotated about y by 20 deg and shifted
    n = np.array([0.1, -0.2, 1.0])
    n /= np.linalg.norm(n)
    d = 12.0
    a = np.deg2rad(20)
    R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    c = np.array([0.5, -0.3, 1.0])
    T = look_pose(R, c)
    # build the plane as a big quad
    e1 = np.cross(n, [1, 0, 0]); e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    p0 = n * d
    s = 500.0
    v = np.stack([p0 - s * e1 - s * e2, p0 + s * e1 - s * e2, p0 + s * e1 + s * e2, p0 - s * e1 + s * e2])
    depth, valid = render_depth((v, np.array([[0, 1, 2], [0, 2, 3]])), K, T[None], H, W)
    x, y = rays(K, H, W)
    d_world = np.stack([x, y, np.ones_like(x)], -1) @ R  # R^T d for each ray
    z = (d - n @ c) / (d_world @ n)
    assert valid.all()
    np.testing.assert_allclose(depth[0], z, rtol=1e-4)


def test_cylinder_seen_from_axis_matches_analytic_depth():
    radius, length = 5.0, 40.0
    r = MeshRenderer(cylinder_mesh(radius, length, rings=41))
    out = r.render(K, np.eye(4), H, W)
    x, y = rays(K, H, W)
    expected = np.minimum(radius / np.sqrt(x**2 + y**2), length)
    assert out["hit"].all()
    np.testing.assert_allclose(out["depth"], expected, rtol=1e-4)
    # interpolated normals are radial on the wall
    wall = expected < length * 0.8
    p = out["points_world"][wall]
    nrm = out["normals_world"][wall]
    radial = p[:, :2] / np.linalg.norm(p[:, :2], axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(nrm[:, :2] * radial, 1)), 1, atol=1e-3)


def test_backprojected_depth_lies_on_mesh():
    # square-ish triangles: Open3D's compute_distance is off by ~1e-3 mm on long slivers
    r = MeshRenderer(cylinder_mesh(4.0, 30.0, n=64, rings=80))
    a = np.deg2rad(10)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    T = look_pose(R, np.array([0.7, -0.4, 2.0]))
    out = r.render(K, T, H, W)
    x, y = rays(K, H, W)
    pc = np.stack([x, y, np.ones_like(x)], -1) * out["depth"][..., None]
    pw = (pc[out["hit"]] - T[:3, 3]) @ T[:3, :3]
    assert r.distance(pw).max() < 1e-3
    np.testing.assert_allclose(pw, out["points_world"][out["hit"]], atol=1e-3)


def test_render_depth_mask_nan_pose_and_miss():
    v, f = plane_mesh(5.0, half=2.0)
    T = np.stack([np.eye(4), np.full((4, 4), np.nan), np.eye(4)])
    T[2, :3, 3] = [0, 0, -5.0]  # further back: 10 mm
    mask = np.zeros((H, W), bool)
    mask[5:40, 5:60] = True
    depth, valid = render_depth((v, f), K, T, H, W, mask=mask)
    assert depth.shape == (3, H, W) and depth.dtype == np.float32 and valid.dtype == bool
    assert not valid[1].any() and (depth[1] == 0).all()
    assert not valid[:, ~mask].any() and (depth[:, ~mask] == 0).all()
    # the small plane does not fill the view: misses are invalid
    assert valid[0].any() and not valid[0][mask].all()
    np.testing.assert_allclose(depth[0][valid[0]], 5.0, rtol=1e-5)
    np.testing.assert_allclose(depth[2][valid[2]], 10.0, rtol=1e-5)


def test_render_depth_torch_in_torch_out():
    torch = pytest.importorskip("torch")
    T = torch.eye(4, dtype=torch.float64)[None].repeat(2, 1, 1)
    depth, valid = render_depth(MeshRenderer(plane_mesh(3.0)), torch.from_numpy(K), T, H, W)
    assert isinstance(depth, torch.Tensor) and depth.shape == (2, H, W) and valid.all()


def test_bad_inputs():
    with pytest.raises(InputError):
        MeshRenderer("/nonexistent/mesh.ply")
    with pytest.raises(InputError):
        MeshRenderer((np.zeros((3, 3)), np.array([[0, 1, 5]])))
    with pytest.raises(ValueError, match=r"cam_from_world must be \(N, 4, 4\)"):
        render_depth(plane_mesh(1.0), K, np.eye(4), H, W)  # needs (N, 4, 4)


def test_accepts_open3d_meshes_and_ply(tmp_path):
    import open3d as o3d

    v, f = plane_mesh(4.0)
    legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    tensor = o3d.t.geometry.TriangleMesh.from_legacy(legacy)
    o3d.io.write_triangle_mesh(str(tmp_path / "p.ply"), legacy)
    for m in (legacy, tensor, tmp_path / "p.ply", str(tmp_path / "p.ply")):
        depth, valid = render_depth(m, K, np.eye(4)[None], H, W)
        assert valid.all()
        np.testing.assert_allclose(depth, 4.0, rtol=1e-5)


def test_normals_interpolate_each_triangles_own_corner_normals():
    """The normal at a hit is (1-u-v) n0 + u n1 + v n2 of *its* triangle's corners, normalised (float64
    reference): corners in another order, or another triangle's, would fail on a coarse curved mesh."""
    v, f = cylinder_mesh(3.0, 10.0, n=12, rings=4)
    r = MeshRenderer((v, f))
    T = look_pose(np.eye(3), np.array([0.4, -0.3, 0.5]))
    out = r.render(K, T, H, W)
    hit = out["hit"]
    assert hit.mean() > 0.9
    ids, uvs = out["triangle_ids"][hit], out["uvs"][hit].astype(np.float64)
    n = r.normals[f[ids]]  # (M, 3 corners, 3)
    ref = (1 - uvs[:, :1] - uvs[:, 1:]) * n[:, 0] + uvs[:, :1] * n[:, 1] + uvs[:, 1:] * n[:, 2]
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(out["normals_world"][hit], ref, atol=1e-5)
    assert np.all(out["normals_world"][~hit] == 0)
    # the coarse mesh's normals do vary across a triangle, so the test sees the interpolation
    assert np.ptp(ref[:, 0]) > 0.5

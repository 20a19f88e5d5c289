import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endorecon.evaluation import ReferenceSurface, Sim3, icp_sim3, register, sample_points, trajectory_candidates


def _extent(mesh):
    v = np.asarray(mesh.vertices)
    return float(np.linalg.norm(v.max(0) - v.min(0)))


def test_sim3_algebra():
    rng = np.random.default_rng(0)
    A = Sim3(2.0, Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix(), np.array([1.0, -2.0, 3.0]))
    B = Sim3(0.5, Rotation.from_rotvec([-0.4, 0.0, 0.7]).as_matrix(), np.array([0.0, 5.0, -1.0]))
    p = rng.normal(size=(10, 3))
    assert np.allclose((A @ B).apply(p), A.apply(B.apply(p)))
    assert np.allclose(A.inverse().apply(A.apply(p)), p)
    hom = np.c_[p, np.ones(10)] @ A.matrix().T
    assert np.allclose(hom[:, :3], A.apply(p))


def test_sample_points_area_uniform_and_seeded(helpers):
    import open3d as o3d

    # A 2x1 rectangle made of a big and a small triangle pair: samples must follow area, not triangle count.
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    tri = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(tri))
    p = sample_points(mesh, 20000, seed=3)
    assert p.shape == (20000, 3) and np.allclose(p[:, 2], 0)
    assert p[:, 0].min() >= 0 and p[:, 0].max() <= 2 and p[:, 1].min() >= 0 and p[:, 1].max() <= 1
    assert abs((p[:, 0] < 1).mean() - 0.5) < 0.02
    assert abs((p[:, 1] < 0.5).mean() - 0.5) < 0.02  # uniform inside each triangle too
    assert np.array_equal(p, sample_points(mesh, 20000, seed=3))
    assert not np.array_equal(p, sample_points(mesh, 20000, seed=4))


def test_sample_points_do_not_depend_on_storage_order(helpers):
    import open3d as o3d

    rng = np.random.default_rng(1)
    v = rng.normal(size=(30, 3))
    tri = np.array([rng.choice(30, 3, replace=False) for _ in range(40)])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(tri))
    # the same surface: vertices permuted, triangles shuffled, each rotated cyclically (orientation kept)
    perm = rng.permutation(30)
    new_index = np.argsort(perm)
    tri2 = new_index[tri][rng.permutation(40)]
    tri2 = np.stack([np.roll(t, k) for t, k in zip(tri2, rng.integers(0, 3, 40))])
    moved = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v[perm]), o3d.utility.Vector3iVector(tri2))
    assert np.array_equal(sample_points(mesh, 5000, seed=2), sample_points(moved, 5000, seed=2))


def test_global_registration_recovers_known_similarity(ct_mesh, recon_from_ct, helpers):
    recon = helpers.moved_mesh(ct_mesh, recon_from_ct)
    src = sample_points(recon, 4000, seed=0)
    ref = sample_points(ct_mesh, 4000, seed=1)
    res = register(src, ReferenceSurface(ct_mesh), ref_points=ref, seed=0)
    assert res.init == "global" and res.converged
    err = helpers.sim3_errors(res.ref_from_recon, recon_from_ct.inverse(), _extent(ct_mesh))
    assert err["scale"] < 1e-3 and err["R"] < 1e-3 and err["t"] < 1e-3, err


def test_trajectory_init_recovers_known_similarity(ct_mesh, recon_from_ct, helpers):
    rng = np.random.default_rng(0)
    recon = helpers.moved_mesh(ct_mesh, recon_from_ct)
    src = sample_points(recon, 4000, seed=0)
    v = np.asarray(ct_mesh.vertices)
    gt_centers = v.mean(0) + rng.normal(size=(20, 3)) * v.std(0) * 0.3
    # A noisy reconstructed trajectory: the initial guess is off, ICP has to finish the job.
    cam_centers = recon_from_ct.apply(gt_centers + rng.normal(scale=1.0, size=gt_centers.shape))
    surface = ReferenceSurface(ct_mesh)
    res = register(src, surface, cam_centers=cam_centers, gt_cam_centers=gt_centers)
    assert res.init == "trajectory"
    truth = recon_from_ct.inverse()
    init = trajectory_candidates(cam_centers, gt_centers)[0]
    err0 = helpers.sim3_errors(init, truth, _extent(ct_mesh))
    assert max(err0.values()) > 1e-2  # the test is not trivial
    err = helpers.sim3_errors(res.ref_from_recon, truth, _extent(ct_mesh))
    assert err["scale"] < 1e-3 and err["R"] < 1e-3 and err["t"] < 1e-3, err


@pytest.mark.parametrize("with_rotations", [False, True])
def test_straight_trajectory_roll_is_resolved(ct_mesh, recon_from_ct, helpers, with_rotations):
    # Camera centres on a line leave the roll about it free; the candidates must still find the pose.
    recon = helpers.moved_mesh(ct_mesh, recon_from_ct)
    src = sample_points(recon, 3000, seed=0)
    v = np.asarray(ct_mesh.vertices)
    axis = np.linalg.svd(v - v.mean(0), full_matrices=False)[2][0]
    gt_centers = v.mean(0) + np.linspace(-10, 10, 12)[:, None] * axis
    cam_centers = recon_from_ct.apply(gt_centers)
    kw = {}
    if with_rotations:
        gt_R = Rotation.random(12, random_state=1).as_matrix()  # cam_from_ct
        kw = dict(gt_cam_rotations=gt_R, cam_rotations=gt_R @ recon_from_ct.R.T)  # cam_from_recon
    cands = trajectory_candidates(cam_centers, gt_centers, **kw)
    assert len(cands) == 8 + int(with_rotations)
    if with_rotations:
        assert np.allclose(cands[1].R, recon_from_ct.inverse().R, atol=1e-9)
        assert abs(cands[1].scale / recon_from_ct.inverse().scale - 1) < 1e-9
    res = register(src, ReferenceSurface(ct_mesh), cam_centers=cam_centers, gt_cam_centers=gt_centers, **kw)
    err = helpers.sim3_errors(res.ref_from_recon, recon_from_ct.inverse(), _extent(ct_mesh))
    assert err["scale"] < 1e-3 and err["R"] < 1e-3 and err["t"] < 1e-3, err


def test_icp_rejects_outliers(ct_mesh, recon_from_ct, helpers):
    rng = np.random.default_rng(2)
    truth = recon_from_ct.inverse()
    src = recon_from_ct.apply(sample_points(ct_mesh, 3000, seed=0))
    lo, hi = src.min(0), src.max(0)
    outliers = rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo), size=(300, 3))  # 10 % junk
    pert = Sim3(1.03, Rotation.from_rotvec([0.04, -0.03, 0.05]).as_matrix(), np.array([1.0, -0.5, 0.8]))
    res = icp_sim3(np.r_[src, outliers], ReferenceSurface(ct_mesh), pert @ truth)
    err = helpers.sim3_errors(res.ref_from_recon, truth, _extent(ct_mesh))
    assert err["scale"] < 1e-3 and err["R"] < 1e-3 and err["t"] < 1e-3, err
    assert 0.85 < res.fitness < 0.95  # the junk is out, the surface points are in


def test_register_rejects_bad_arguments(ct_mesh):
    src = sample_points(ct_mesh, 100, seed=0)
    surface = ReferenceSurface(ct_mesh)
    with pytest.raises(ValueError, match="cam_centers"):
        register(src, surface, init="trajectory")
    with pytest.raises(ValueError, match="ref_points"):
        register(src, surface, init="global")
    with pytest.raises(ValueError, match="unknown init"):
        register(src, surface, init="magic")
    with pytest.raises(ValueError, match="at least 3"):
        register(src, surface, cam_centers=np.zeros((2, 3)), gt_cam_centers=np.zeros((2, 3)))
    bad = src.copy()
    bad[:5] = np.nan  # the NaN median distance made every point an outlier: the init came back, "not converged"
    with pytest.raises(ValueError, match="non-finite"):
        icp_sim3(bad, surface, Sim3.identity())
    with pytest.raises(ValueError, match="scale > 0"):
        icp_sim3(src, surface, Sim3(0.0, np.eye(3), np.zeros(3)))

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from omegaconf import OmegaConf

from endorecon.data.sequence import write_poses_txt
from endorecon.evaluation import evaluate_mesh, load_mesh, residual_stats
from endorecon.tasks.evaluate import run
from endorecon.utils.errors import InputError

CONF = Path(__file__).resolve().parents[2] / "conf"


def _write(mesh, path):
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def test_residual_stats_analytic():
    r = np.arange(101) / 50.0  # 0 .. 2 mm
    s = residual_stats(r)
    assert s["mean_mm"] == pytest.approx(1.0) and s["median_mm"] == pytest.approx(1.0)
    assert s["p95_mm"] == pytest.approx(1.9) and s["max_mm"] == pytest.approx(2.0)
    assert s["frac_below_1mm"] == pytest.approx(50 / 101) and s["n_points"] == 101
    assert s["rmse_mm"] == pytest.approx(np.sqrt((r**2).mean()))


def test_mesh_against_itself(ct_path, tmp_path):
    m = evaluate_mesh(ct_path, ct_path, tmp_path / "out", n_points=3000, seed=0)
    assert m["mean_mm"] < 1e-3 and m["max_mm"] < 1e-2
    assert m["frac_below_1mm"] == 1.0 and m["n_points"] == 3000
    assert abs(m["sim3"]["scale"] - 1) < 1e-4
    for f in ("metrics.json", "residual_heatmap.png", "residual_histogram.png", "residuals.npz"):
        assert (tmp_path / "out" / f).is_file(), f
    on_disk = json.loads((tmp_path / "out" / "metrics.json").read_text())
    for k in ("mean_mm", "median_mm", "p95_mm", "max_mm", "frac_below_1mm", "n_points", "ct_covered_mm2"):
        assert on_disk[k] == m[k]
    assert m["ct_covered_mm2"] == pytest.approx(m["ct_area_mm2"], rel=1e-3)  # a mesh covers all of itself
    assert set(on_disk["sim3"]) >= {"scale", "R", "t"} and "fitness" in on_disk["registration"]


def test_known_normal_offset(tmp_path):
    # Reference: a 20 mm cube.  Reconstruction: a 10x10 mm patch 0.5 mm above its top face.
    cube = o3d.geometry.TriangleMesh.create_box(20.0, 20.0, 20.0)
    patch = o3d.geometry.TriangleMesh.create_box(10.0, 10.0, 1e-3)
    patch.translate([5.0, 5.0, 20.5])
    ref, rec = _write(cube, tmp_path / "cube.ply"), _write(patch, tmp_path / "patch.ply")
    # No registration (identity, no ICP step): the residual measure alone.
    m = evaluate_mesh(rec, ref, tmp_path / "out", n_points=2000, registration={"init": "identity", "max_iter": 0})
    assert m["mean_mm"] == pytest.approx(0.5005, abs=1e-3) and m["max_mm"] == pytest.approx(0.501, abs=1e-3)
    assert m["frac_below_1mm"] == 1.0
    # Lifted by 1.5 mm: nothing is under 1 mm.
    patch.translate([0.0, 0.0, 1.0])
    m = evaluate_mesh(_write(patch, tmp_path / "patch2.ply"), ref, tmp_path / "out2", n_points=2000,
                      registration={"init": "identity", "max_iter": 0})
    assert m["median_mm"] == pytest.approx(1.5, abs=2e-3) and m["frac_below_1mm"] == 0.0


def _open_patch(size: float, n: int, z: float, hole: tuple | None = None) -> o3d.geometry.TriangleMesh:
    """An open n x n grid of squares (two triangles each) over [5, 5 + size]² at height z, without the squares
    whose centres fall in ``hole`` = (x0, x1, y0, y1)."""
    g = np.linspace(0.0, size, n + 1)
    xx, yy = np.meshgrid(g + 5.0, g + 5.0)
    v = np.c_[xx.ravel(), yy.ravel(), np.full(xx.size, z)]
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, i * (n + 1) + j + 1, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1
            cx, cy = v[[a, b, c, d], 0].mean(), v[[a, b, c, d], 1].mean()
            if hole and hole[0] < cx < hole[1] and hole[2] < cy < hole[3]:
                continue
            tris += [[a, b, d], [a, d, c]]
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(np.array(tris)))


def test_coverage_of_a_patch_over_a_cube():
    """The CT area a reconstruction covers, analytically: an open 10x10 mm patch 0.5 mm above a 20 mm cube's top
    face covers the face under it, 100 mm² (not the 1 mm band around it: those CT points' closest point is the
    patch's border); a 2x2 mm hole in it uncovers 4 mm² (by distance alone it counted as covered)."""
    from endorecon.evaluation.evaluate import coverage

    cube = o3d.geometry.TriangleMesh.create_box(20.0, 20.0, 20.0)
    patch = _open_patch(10.0, 20, 20.5)
    c = coverage(patch, cube, n_points=200000, seed=1)
    assert c["ct_area_mm2"] == pytest.approx(2400.0) and c["area_mm2"] == pytest.approx(100.0, rel=1e-6)
    assert c["ct_covered_mm2"] == pytest.approx(100.0, abs=2.5)
    holed = coverage(_open_patch(10.0, 20, 20.5, hole=(9.0, 11.0, 9.0, 11.0)), cube, n_points=200000, seed=1)
    assert holed["area_mm2"] == pytest.approx(96.0, rel=1e-6)
    assert holed["ct_covered_mm2"] == pytest.approx(96.0, abs=2.5)
    # a closed surface has no border: a thin box covers the band within 1 mm, 100 + 40 r + π r², r = sqrt(1 - 0.5²)
    box = o3d.geometry.TriangleMesh.create_box(10.0, 10.0, 1e-3)
    box.translate([5.0, 5.0, 20.5])
    r = np.sqrt(1 - 0.25)
    assert coverage(box, cube, n_points=200000, seed=1)["ct_covered_mm2"] == pytest.approx(100 + 40 * r + np.pi * r**2,
                                                                                            abs=5.0)
    patch.translate([0.0, 0.0, 1.0])  # 1.5 mm above: covers nothing
    assert coverage(patch, cube, n_points=20000)["ct_covered_mm2"] == 0.0


def _tilted_patch_with_std(path, sign):
    # A 10x10 mm patch over the cube's top face, its height above it growing with x (0.2 .. 1.2 mm), and a
    # per-vertex std of +-(that height): a std that ranks the residuals exactly, or exactly backwards.
    from endorecon.fusion.ply import write_mesh_ply

    patch = o3d.geometry.TriangleMesh.create_box(10.0, 10.0, 1e-3).subdivide_midpoint(3)
    v = np.asarray(patch.vertices).copy()
    v[:, 0] += 5.0
    v[:, 1] += 5.0
    height = 0.2 + 0.1 * (v[:, 0] - 5.0)
    v[:, 2] = 20.0 + height + v[:, 2]
    tm = o3d.t.geometry.TriangleMesh()
    tm.vertex.positions = o3d.core.Tensor(v.astype(np.float32))
    tm.triangle.indices = o3d.core.Tensor(np.asarray(patch.triangles).astype(np.int32))
    tm.vertex["std"] = o3d.core.Tensor((sign * height)[:, None].astype(np.float32))
    return write_mesh_ply(path, tm)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_std_residual_spearman(sign, tmp_path):
    ref = _write(o3d.geometry.TriangleMesh.create_box(20.0, 20.0, 20.0), tmp_path / "cube.ply")
    rec = _tilted_patch_with_std(tmp_path / f"patch{sign:+.0f}.ply", sign)
    m = evaluate_mesh(rec, ref, tmp_path / "out", n_points=2000, registration={"init": "identity", "max_iter": 0})
    # Distinct heights tie only within a column of vertices, so rho is near, not at, +-1.
    assert m["std_residual_spearman"] == pytest.approx(sign, abs=0.02)
    # The same surface without a std (any other mesh): no ranking, stated as None.
    plain = _write(load_mesh(rec), tmp_path / "plain.ply")
    m = evaluate_mesh(plain, ref, tmp_path / "out_plain", n_points=2000, registration={"init": "identity", "max_iter": 0})
    assert m["std_residual_spearman"] is None


def test_noisy_moved_reconstruction(ct_mesh, recon_from_ct, helpers, tmp_path):
    # A reconstruction with 0.2 mm normal noise, in arbitrary units: the residual is that noise, in mm.
    rng = np.random.default_rng(0)
    fine = ct_mesh.subdivide_midpoint(1)
    fine.compute_vertex_normals()
    v = np.asarray(fine.vertices) + np.asarray(fine.vertex_normals) * rng.normal(0, 0.2, (len(fine.vertices), 1))
    fine.vertices = o3d.utility.Vector3dVector(v)
    noisy = helpers.moved_mesh(fine, recon_from_ct)
    m = evaluate_mesh(_write(noisy, tmp_path / "noisy.ply"), _write(ct_mesh, tmp_path / "ct.ply"),
                      tmp_path / "out", n_points=4000)
    assert 0.05 < m["mean_mm"] < 0.2 and m["max_mm"] < 1.0
    assert abs(m["sim3"]["scale"] * recon_from_ct.scale - 1) < 5e-3


def test_skips_complete_output_and_recomputes_on_change(ct_path, tmp_path):
    out = tmp_path / "out"
    evaluate_mesh(ct_path, ct_path, out, n_points=1000, registration={"init": "identity"})
    stamp = (out / "metrics.json").stat().st_mtime_ns
    evaluate_mesh(ct_path, ct_path, out, n_points=1000, registration={"init": "identity"})
    assert (out / "metrics.json").stat().st_mtime_ns == stamp
    m = evaluate_mesh(ct_path, ct_path, out, n_points=1200, registration={"init": "identity"})
    assert m["n_points"] == 1200 and (out / "metrics.json").stat().st_mtime_ns != stamp
    # an output missing (the residuals) or another colour scale for the heat-map: made again
    (out / "residuals.npz").unlink()
    evaluate_mesh(ct_path, ct_path, out, n_points=1200, registration={"init": "identity"})
    assert (out / "residuals.npz").is_file()
    heat = (out / "residual_heatmap.png").stat().st_mtime_ns
    evaluate_mesh(ct_path, ct_path, out, n_points=1200, registration={"init": "identity"}, vmax_mm=3.0)
    assert (out / "residual_heatmap.png").stat().st_mtime_ns != heat


def test_coincident_camera_centres_are_an_error_not_nan(ct_path, tmp_path):
    centres = np.zeros((5, 3))
    gt = np.random.default_rng(0).normal(size=(5, 3))
    with pytest.raises((InputError, ValueError), match="coincide"):
        evaluate_mesh(ct_path, ct_path, tmp_path / "out", n_points=500, cam_centers=centres, gt_cam_centers=gt)
    assert not (tmp_path / "out" / "metrics.json").exists()
    # the ground truth's centres coinciding: the least-squares scale was 0 and ICP divided by it
    with pytest.raises(InputError, match="coincide"):
        evaluate_mesh(ct_path, ct_path, tmp_path / "out", n_points=500, cam_centers=gt, gt_cam_centers=centres)
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_residual_stats_refuse_non_finite():
    with pytest.raises(ValueError, match="not finite"):
        residual_stats(np.array([0.1, np.nan, 0.3]))


@pytest.mark.parametrize("case", ["missing", "empty", "text", "point_cloud", "extension"])
def test_bad_mesh_inputs_name_the_file(case, ct_path, tmp_path):
    bad = tmp_path / f"bad_{case}.ply"
    if case == "empty":
        bad.write_bytes(b"")
    elif case == "text":
        bad.write_text("this is not a mesh\n")
    elif case == "point_cloud":
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).normal(size=(50, 3))))
        o3d.io.write_point_cloud(str(bad), pcd)
    elif case == "extension":
        bad = tmp_path / "bad_extension.npy"
        bad.write_bytes(b"\x93NUMPY")
    with pytest.raises(InputError) as e:
        load_mesh(bad)
    assert bad.name in str(e.value) and e.value.path == bad
    for kw in ({"mesh_path": bad, "reference_path": ct_path}, {"mesh_path": ct_path, "reference_path": bad}):
        with pytest.raises(InputError, match=bad.name):
            evaluate_mesh(out_dir=tmp_path / "out", n_points=100, **kw)


def _cfg(**kw):
    cfg = OmegaConf.load(CONF / "evaluate.yaml")
    cfg.pop("defaults")
    cfg.pop("hydra")
    cfg.merge_with(kw)
    return cfg


def test_task_with_trajectory(ct_mesh, ct_path, recon_from_ct, helpers, tmp_path, capsys):
    rng = np.random.default_rng(1)
    rec = _write(helpers.moved_mesh(ct_mesh, recon_from_ct), tmp_path / "recon.ply")
    v = np.asarray(ct_mesh.vertices)
    centers = v.mean(0) + rng.normal(size=(6, 3)) * v.std(0) * 0.3
    from scipy.spatial.transform import Rotation

    R_gt = Rotation.random(6, random_state=2).as_matrix()  # cam_from_ct
    T_gt = np.tile(np.eye(4), (6, 1, 1))
    T_gt[:, :3, :3] = R_gt
    T_gt[:, :3, 3] = -np.einsum("kij,kj->ki", R_gt, centers)
    # Same cameras in the reconstruction's frame: cam_from_recon = cam_from_ct @ ct_from_recon.
    ct_from_recon = recon_from_ct.inverse().matrix()
    T_rec = T_gt @ ct_from_recon
    T_rec[:, :3, :] /= recon_from_ct.inverse().scale  # make the rotation part orthonormal again
    T_rec[:, 3] = [0, 0, 0, 1]
    names = [f"{i:04d}.png" for i in range(6)]
    T_rec_nan = T_rec.copy()
    T_rec_nan[5] = np.nan  # an unregistered frame is skipped
    p_rec = write_poses_txt(tmp_path / "poses.txt", names, T_rec_nan)
    p_gt = write_poses_txt(tmp_path / "gt_poses.txt", names, T_gt)
    cfg = _cfg(mesh=str(rec), reference=str(ct_path), trajectory=str(p_rec), gt_trajectory=str(p_gt),
               out=str(tmp_path / "out"), n_points=2000)
    out = run(cfg)
    m = json.loads((out / "metrics.json").read_text())
    assert m["registration"]["init"] == "trajectory"
    assert m["mean_mm"] < 1e-3 and abs(m["sim3"]["scale"] * 0.37 - 1) < 1e-4
    assert "mean" in capsys.readouterr().out
    # a trajectory that shares too few frames with the ground truth
    write_poses_txt(tmp_path / "few.txt", names[:2], T_rec[:2])
    with pytest.raises(InputError, match="few.txt"):
        run(_cfg(mesh=str(rec), reference=str(ct_path), trajectory=str(tmp_path / "few.txt"),
                 gt_trajectory=str(p_gt), out=str(tmp_path / "out3"), n_points=500))
    with pytest.raises(InputError, match="gt_trajectory"):
        run(_cfg(mesh=str(rec), reference=str(ct_path), trajectory=str(p_rec), out=str(tmp_path / "o4")))
    # a trajectory of a camera that never moved: no scale, an error naming it (not a NaN registration)
    still = np.tile(T_rec[:1], (6, 1, 1))
    write_poses_txt(tmp_path / "still.txt", names, still)
    with pytest.raises(InputError, match="coincide") as e:
        run(_cfg(mesh=str(rec), reference=str(ct_path), trajectory=str(tmp_path / "still.txt"),
                 gt_trajectory=str(p_gt), out=str(tmp_path / "o5"), n_points=500))
    assert e.value.path.name == "still.txt"


def test_bad_registration_init_is_named_before_any_work(ct_path, tmp_path, monkeypatch):
    """A misspelt registration.init, or init=trajectory without trajectories: an InputError naming the key
    (exit status 2), not a ValueError traceback after the meshes were read and sampled."""
    import endorecon.tasks.evaluate as task

    monkeypatch.setattr(task, "evaluate_mesh", lambda *a, **k: pytest.fail("evaluated with a bad init"))
    for missing in ("mesh", "reference"):  # a traceback (MissingMandatoryValue) before
        cfg = _cfg(**{k: str(ct_path) for k in ("mesh", "reference") if k != missing}, out=str(tmp_path / "o"))
        with pytest.raises(InputError, match=f"{missing}= is required"):
            run(cfg)
    for init, match in (("globl", "registration.init='globl' is not one of"),
                        ("trajectory", "registration.init=trajectory needs")):
        cfg = _cfg(mesh=str(ct_path), reference=str(ct_path), out=str(tmp_path / "o"), registration={"init": init})
        with pytest.raises(InputError, match=match):
            run(cfg)
    assert not (tmp_path / "o").exists()


def test_config_composes(tmp_path):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("evaluate", overrides=["mesh=a.ply", "reference=b.ply", f"out={tmp_path}"])
    assert cfg.n_points == 40000 and cfg.registration.init == "auto" and cfg.out == str(tmp_path)


def test_heat_map_views_show_the_whole_of_a_long_mesh():
    """The views put the mesh's longest axis along the image's shorter side (the height): sized by the
    horizontal field of view, a 10x2x1 box lost ~9 % of its length off the top and bottom edges."""
    from endorecon.evaluation.plots import render_scalar_views

    box = o3d.geometry.TriangleMesh.create_box(10.0, 2.0, 1.0)
    images = render_scalar_views(box, np.zeros(len(box.vertices)), vmax=1.0, n_views=3, width=400, height=320)
    for img in images:
        drawn = (img < 0.99).any(axis=2)
        assert drawn.any()
        assert not drawn[0].any() and not drawn[-1].any() and not drawn[:, 0].any() and not drawn[:, -1].any()


def test_heat_map_says_when_its_colour_scale_clips(tmp_path, monkeypatch):
    """Residuals above the colour bar's top were drawn in its top colour without a word: the worst patch of a
    mesh looked like 1.5 mm when it was 3 mm."""
    import matplotlib.figure

    from endorecon.evaluation.plots import save_residual_heatmap

    seen = {}
    real_title, real_bar = matplotlib.figure.Figure.suptitle, matplotlib.figure.Figure.colorbar
    monkeypatch.setattr(matplotlib.figure.Figure, "suptitle",
                        lambda self, t, **k: seen.update(title=t) or real_title(self, t, **k))
    monkeypatch.setattr(matplotlib.figure.Figure, "colorbar",
                        lambda self, *a, **k: seen.update(extend=k.get("extend")) or real_bar(self, *a, **k))
    sphere = o3d.geometry.TriangleMesh.create_sphere(5.0, 10)
    res = np.full(len(sphere.vertices), 0.2)
    res[:7] = 3.0
    save_residual_heatmap(sphere, res, tmp_path / "h.png", vmax_mm=1.5, n_views=1, title="m")
    assert seen["extend"] == "max" and "clipped at 1.50 mm: 7 of" in seen["title"] and "up to 3.000 mm" in seen["title"]
    save_residual_heatmap(sphere, np.full(len(sphere.vertices), 0.2), tmp_path / "h2.png", n_views=1, title="m")
    assert seen["extend"] == "neither" and seen["title"] == "m"

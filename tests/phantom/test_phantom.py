"""Phantom: layout and importers, GT consistency, determinism, conventions, bad input (tiny sizes)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from endorecon.data.dataset import load_dataset, load_ground_truth, patients_with_ct
from endorecon.geometry import invert_pose, project, transform_points, unproject
from endorecon.phantom import VERSION, ensure_dataset, generate
from endorecon.phantom.anatomy import make_anatomy
from endorecon.phantom.trajectory import endoscope_camera
from endorecon.rendering import MeshRenderer
from endorecon.utils.errors import InputError

H, W = 48, 64
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("ph") / "ds", patients=5, frames=3, height=H, width=W, seed=3)


def test_layout_and_importers_read_back(ds):
    meta = json.loads((ds / "dataset.json").read_text())
    assert meta["format"] == "endorecon-phantom" and meta["version"] == VERSION and meta["units"] == "mm"
    assert (meta["height"], meta["width"], meta["seed"]) == (H, W, 3)
    assert [p["has_ct"] for p in meta["patients"]] == [True] * 4 + [False]
    assert (ds / "COMPLETE").is_file()
    assert patients_with_ct(ds) == [0, 1, 2, 3]
    seqs = load_dataset(ds)
    assert [s.name for s in seqs] == [f"patient_{p:02d}/seq_00" for p in range(5)]
    K, mask = endoscope_camera(H, W)
    for p, s in enumerate(seqs):
        assert s.patient == p and s.source == "phantom" and s.units == "mm" and len(s) == 3
        np.testing.assert_allclose(s.intrinsics, K)
        np.testing.assert_array_equal(s.mask, mask)
        assert not s.registered.any()  # the pipeline gets no poses
        img = s.load_frame(0)
        assert img.shape == (H, W, 3) and img[~mask].mean() < 5 and img[mask].mean() > 40  # JPEG rings a little at the rim
    gt = load_ground_truth(ds, 0)
    assert gt.depth_mm.shape == (3, H, W) and gt.depth_mm.dtype == np.float32
    assert gt.cam_from_world.shape == (3, 4, 4) and gt.mesh_path.is_file()
    assert (gt.depth_mm[:, ~mask] == 0).all() and (gt.depth_mm[:, mask] > 0).mean() > 0.99
    assert load_ground_truth(ds, 4).mesh_path is None  # train-only patient: no CT for evaluation
    with pytest.raises(InputError, match="no patient 7"):
        load_ground_truth(ds, 7)
    with pytest.raises(InputError, match=r"patient 0 has no sequence 'seq_05'"):
        load_ground_truth(ds, 0, "seq_05")


def test_gt_depth_backprojects_onto_gt_mesh(ds):
    K, mask = endoscope_camera(H, W)
    for p in (0, 2):
        gt = load_ground_truth(ds, p)
        r = MeshRenderer(gt.mesh_path)
        d = torch.from_numpy(gt.depth_mm)[:, None].double()
        Kt = torch.from_numpy(K)[None].expand(len(d), 3, 3)
        pts_cam = unproject(d, Kt).flatten(2).transpose(1, 2)  # (N, HW, 3)
        pts_w = transform_points(invert_pose(torch.from_numpy(gt.cam_from_world)), pts_cam)
        valid = gt.depth_mm.reshape(len(d), -1) > 0
        dist = r.distance(pts_w.numpy()[valid])
        assert valid.sum() > 0.99 * mask.sum() * len(d)
        assert dist.max() < 0.01, dist.max()


def test_conventions_agree_with_geometry_core():
    a = make_anatomy(5, length_mm=60)
    r = MeshRenderer((a.vertices, a.triangles))
    K, _ = endoscope_camera(H, W)
    from endorecon.phantom.trajectory import plan_trajectory

    T = plan_trajectory(a.centreline, a.clearance, 2, np.random.default_rng(0))[0]
    out = r.render(K, T, H, W)
    Tt = torch.from_numpy(T)[None]
    # every rendered surface point projects back to the centre of its own pixel
    pw = torch.from_numpy(out["points_world"][out["hit"]].astype(np.float64))[None]
    uv, z = project(transform_points(Tt, pw), torch.from_numpy(K)[None])
    v, u = np.nonzero(out["hit"])
    np.testing.assert_allclose(uv[0].numpy(), np.stack([u, v], 1), atol=2e-3)
    np.testing.assert_allclose(z[0].numpy(), out["depth"][out["hit"]], rtol=1e-5)
    # a mesh vertex seen by the camera is found at the pixel the core projects it to
    vc = transform_points(Tt, torch.from_numpy(a.vertices)[None])
    uv, z = project(vc, torch.from_numpy(K)[None])
    uv, z = uv[0].numpy(), z[0].numpy()
    px = np.round(uv).astype(int)
    inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
    idx = np.flatnonzero(inside)
    rendered = out["depth"][px[idx, 1], px[idx, 0]]
    visible = idx[np.abs(rendered - z[idx]) < 0.02 * z[idx]]
    assert len(visible) > 20
    footprint = z[visible] / K[0, 0]  # one pixel on the surface, fronto-parallel
    hit_pts = out["points_world"][px[visible, 1], px[visible, 0]]
    err = np.linalg.norm(hit_pts - a.vertices[visible], axis=1) / footprint
    assert np.median(err) < 0.75  # within a pixel (grazing views stretch it), most much closer


def test_same_seed_same_bytes_other_seed_other_anatomy(tmp_path):
    kw = dict(patients=1, frames=2, height=H, width=W)
    a = generate(tmp_path / "a", seed=11, **kw)
    b = generate(tmp_path / "b", seed=11, **kw)
    c = generate(tmp_path / "c", seed=12, **kw)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) >= 8
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    assert (a / "ground_truth/patient_00/mesh.ply").read_bytes() != (c / "ground_truth/patient_00/mesh.ply").read_bytes()
    va, vc = make_anatomy(1).vertices, make_anatomy(2).vertices
    assert va.shape == vc.shape and np.abs(va - vc).mean() > 1.0  # mm: really another anatomy


def test_anatomy_is_a_watertight_irregular_passage():
    a = make_anatomy(4)
    # closed and consistently oriented: every directed edge appears once and its reverse once
    # (open3d's is_watertight also tests self-intersection, which takes ~70 s here)
    f = a.triangles
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = e[:, 0] * len(a.vertices) + e[:, 1]
    rev = e[:, 1] * len(a.vertices) + e[:, 0]
    assert len(np.unique(key)) == len(key) and np.isin(rev, key).all()
    assert np.setdiff1d(np.arange(len(a.vertices)), f).size == 0
    # cross-sections 8-30 mm across in the middle part, and not circular
    rad = np.linalg.norm(a.vertices[: len(a.centreline) * 192].reshape(len(a.centreline), 192, 3) - a.centreline[:, None], axis=2)
    mid = rad[len(rad) // 5 : -len(rad) // 5]
    widths = mid.max(1) + mid[:, ::-1].max(1)
    assert 8 <= np.median(2 * mid.mean(1)) <= 30 and widths.max() <= 2 * 30
    assert np.median(mid.std(1) / mid.mean(1)) > 0.08
    # the camera path (centreline) is inside the closed surface
    r = MeshRenderer((a.vertices, a.triangles))
    assert r.occupancy(a.centreline[10:-10]).all()


def test_ensure_dataset_reuses_and_bad_input(tmp_path):
    cfg = dict(root=str(tmp_path / "c"), patients=1, frames=2, height=H, width=W, seed=0)
    root = ensure_dataset(cfg)
    stamp = (root / "COMPLETE").stat().st_mtime_ns
    assert ensure_dataset(cfg) == root and (root / "COMPLETE").stat().st_mtime_ns == stamp
    # a dataset drawn by an older generator, or with other motion settings, is made again
    meta = json.loads((root / "dataset.json").read_text())
    (root / "dataset.json").write_text(json.dumps({**meta, "generator": meta["generator"] - 1}))
    ensure_dataset(cfg)
    assert json.loads((root / "dataset.json").read_text()) == meta
    stamp = (root / "COMPLETE").stat().st_mtime_ns
    ensure_dataset({**cfg, "step_mm": 0.2})
    assert json.loads((root / "dataset.json").read_text())["step_mm"] == 0.2
    assert (root / "COMPLETE").stat().st_mtime_ns != stamp
    # the JPEG quality reaches the generator and is checked (it was dropped: the default frames reused)
    assert "jpeg_quality" not in json.loads((root / "dataset.json").read_text())  # default: dataset.json as before
    size = (root / "patient_00" / "seq_00" / "frames" / "000000.jpg").stat().st_size
    ensure_dataset({**cfg, "step_mm": 0.2, "jpeg_quality": 20})
    assert json.loads((root / "dataset.json").read_text())["jpeg_quality"] == 20
    assert (root / "patient_00" / "seq_00" / "frames" / "000000.jpg").stat().st_size < size
    with pytest.raises(InputError, match="jpeg_qualty"):
        ensure_dataset({**cfg, "jpeg_qualty": 20})
    with pytest.raises(InputError):
        load_dataset(tmp_path / "missing")
    (root / "COMPLETE").unlink()
    with pytest.raises(InputError, match="incomplete"):
        load_dataset(root)
    with pytest.raises(InputError):
        generate(tmp_path / "x", frames=1)
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "thesis.txt").write_text("keep me")
    with pytest.raises(InputError, match="not a phantom"):
        generate(tmp_path / "precious", patients=1, frames=2, height=H, width=W)
    assert (tmp_path / "precious" / "thesis.txt").read_text() == "keep me"
    with pytest.raises(InputError):
        generate(tmp_path / "x", patients=1, frames=2, mesh=tmp_path / "nope.ply")


def test_config_files_repeat_the_generators_defaults(monkeypatch):
    """conf/phantom.yaml (the command line) and conf/data/phantom.yaml (training) state the generator's defaults."""
    import yaml

    from endorecon.phantom import __main__ as cli
    from endorecon.phantom.generate import DEFAULT_PATIENTS, generator_defaults

    d = generator_defaults()
    assert d["patients"] == DEFAULT_PATIENTS
    cli_conf = yaml.safe_load((ROOT / "conf" / "phantom.yaml").read_text())
    assert cli_conf.pop("out") is None
    assert cli_conf == d
    train_conf = yaml.safe_load((ROOT / "conf" / "data" / "phantom.yaml").read_text())["phantom"]
    assert train_conf == d  # every setting can be overridden with data.phantom.<key>=...
    # without conf/ next to the package the command line falls back to the same values
    monkeypatch.setattr(cli, "CONF", ROOT / "no_such_conf.yaml")
    assert cli.parse_args(["out=x"]) == {"out": "x", **d}


def test_cli_rejects_unknown_key(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "endorecon.phantom", f"out={tmp_path}/o", "bogus=1"], cwd=ROOT, capture_output=True, text=True
    )
    assert r.returncode == 2 and "unknown key 'bogus'" in r.stderr
    assert not (tmp_path / "o").exists()


def test_given_mesh_phantom_plans_a_path_inside(tmp_path):
    from endorecon.phantom.generate import _write_mesh
    from endorecon.phantom.trajectory import estimate_centreline

    a = make_anatomy(6, length_mm=60, ds_mm=0.8, n_theta=96)
    ply = tmp_path / "cavity.ply"
    _write_mesh(ply, a.vertices, a.triangles)
    r = MeshRenderer(ply)
    centre, clearance = estimate_centreline(r, voxel_mm=1.5)
    assert r.occupancy(centre).all() and clearance.min() > 1.0
    assert np.linalg.norm(centre[-1] - centre[0]) > 30  # end to end along the passage
    ds = generate(tmp_path / "ds", patients=1, frames=3, height=H, width=W, mesh=ply)
    gt = load_ground_truth(ds, 0)
    K, mask = endoscope_camera(H, W)
    assert (gt.depth_mm[:, mask] > 0).mean() > 0.99  # the camera sees surface everywhere in the circle
    assert json.loads((ds / "dataset.json").read_text())["mesh"] == str(ply.resolve())
    with pytest.raises(InputError, match="waypoints"):
        generate(tmp_path / "bad", patients=1, frames=3, height=H, width=W, mesh=ply, waypoints=[[500, 0, 0], [600, 0, 0]])


def test_motion_blur_keeps_ground_truth(tmp_path):
    kw = dict(patients=1, frames=3, height=H, width=W, seed=2)
    sharp = generate(tmp_path / "s", **kw)
    blur = generate(tmp_path / "b", motion_blur=3, **kw)
    a, b = load_ground_truth(sharp, 0), load_ground_truth(blur, 0)
    np.testing.assert_array_equal(a.cam_from_world, b.cam_from_world)  # blur sub-poses straddle the GT pose
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    fa, fb = load_dataset(sharp)[0].load_frame(1), load_dataset(blur)[0].load_frame(1)
    assert np.abs(fa.astype(int) - fb.astype(int)).mean() > 0.5


def test_contact_sheet_tiles_frames_depth_and_mask(ds, tmp_path):
    from PIL import Image

    from endorecon.phantom.contact_sheet import contact_sheet

    out = contact_sheet(ds, tmp_path / "sheet.png", patients=(0, 1), frames_per_row=3)
    im = Image.open(out)
    # rows: 2 patients; tiles: 3 frames + 2 depth maps + mask, each padded by 2 px
    assert im.size == (6 * (W + 4), 2 * (H + 4))


def _rotation_deg(T: np.ndarray) -> np.ndarray:
    R = T[:, :3, :3]
    rel = np.einsum("nij,nkj->nik", R[1:], R[:-1])
    return np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))


def test_trajectory_moves_like_a_hand_held_scope_at_video_rate():
    """A few tenths of a degree and mm per frame, some backward motion, smooth (SfM on video needs this)."""
    from endorecon.phantom.trajectory import plan_trajectory

    backwards = 0
    for seed in range(4):
        a = make_anatomy(seed)
        T = plan_trajectory(a.centreline, a.clearance, 60, np.random.default_rng(seed))  # default 0.35 mm/frame
        rot = _rotation_deg(T)
        centres = -np.einsum("nji,nj->ni", T[:, :3, :3], T[:, :3, 3])
        fwd = np.einsum("ni,ni->n", np.diff(centres, axis=0), T[:-1, 2, :3])  # along the viewing axis
        assert 0.1 < rot.mean() < 0.8 and rot.max() < 1.5, (seed, rot.mean(), rot.max())
        step = np.linalg.norm(np.diff(centres, axis=0), axis=1)
        assert 0.25 < step.mean() < 0.6 and step.max() < 1.0, (seed, step.mean(), step.max())
        assert fwd.mean() > 0.15
        backwards += int((fwd < 0).any())
        # smooth: the rotation rate changes little from one frame to the next
        assert np.abs(np.diff(rot)).max() < 0.2
    assert backwards >= 2  # back-and-forth: the scope is pulled back now and then


def test_line_band_limiting_keeps_the_ink():
    """A vessel thinner than a pixel is widened and dimmed so that its integrated darkness stays the same."""
    from endorecon.phantom.appearance import _line

    v = np.linspace(-3, 3, 200001)
    dv = v[1] - v[0]
    sharp = _line(v, 0.07, 7.0, np.full_like(v, 1e-4))
    wide = _line(v, 0.07, 7.0, np.full_like(v, 1.0))  # 1 mm pixels: far below the line width
    np.testing.assert_allclose(sharp.max(), 1.0, atol=1e-6)
    assert wide.max() < 0.25  # dimmed
    # the ink integrated over the surface: the field's value v is ~ 4.4 / 7 per mm along the surface
    np.testing.assert_allclose(sharp.sum() * dv, wide.sum() * dv, rtol=1e-3)
    np.testing.assert_allclose(sharp.sum() * dv, 0.07 * np.sqrt(np.pi), rtol=1e-3)


def test_texture_has_detail_at_every_working_distance():
    """Band-limited in screen space: sampled at its pixel footprint, the pattern has similar contrast near and far."""
    from endorecon.phantom.appearance import SolidTexture

    tex = SolidTexture(0)
    stds = []
    for fp in (0.03, 0.06, 0.12, 0.3):  # pixel footprint (mm) at 256x320: a wall at ~3.5 mm ... ~35 mm
        g = np.arange(64) * fp
        uu, vv = np.meshgrid(g, g)
        p = np.stack([uu.ravel(), vv.ravel(), np.zeros(uu.size)], 1) + 3.0
        alb = tex(p, np.full(len(p), fp))["albedo"]
        lum = np.log(alb[:, 1]).reshape(64, 64)
        # detail at the scale of a few pixels: high-pass by the 4x4 block means
        blocks = lum.reshape(16, 4, 16, 4).mean(axis=(1, 3))
        stds.append(float((lum - np.kron(blocks, np.ones((4, 4)))).std()))
    assert min(stds) > 0.05, stds  # visible detail (SIFT needs it) at every distance
    assert max(stds) / min(stds) < 2.0, stds  # and similar near and far (no far blur, no near smoothness)

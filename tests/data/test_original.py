"""Importer of the original method's format: the shipped sinus_example and broken copies of a tiny one."""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from endorecon.data.original import load_original
from endorecon.sfm.clean import inside_mask, project_all
from endorecon.sfm.colmap import read_colmap_model, write_colmap_model
from endorecon.utils.errors import InputError

SINUS = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "sinus_example"


@pytest.fixture(scope="module")
def sinus():
    if not SINUS.is_dir():
        pytest.skip(f"{SINUS} not available")
    return load_original(SINUS)


def test_sinus_example_imports(sinus):
    assert len(sinus) == 35 and sinus.registered.all()
    assert (sinus.height, sinus.width) == (1080, 1920)
    assert sinus.source == "original" and sinus.units == "sfm"
    assert len(sinus.points_xyz) == 570 and all(len(v) >= 1 for v in sinus.visibility)
    # camera_intrinsics_per_view is in COLMAP's corner convention: cx, cy - 0.5 here
    vals = np.array((SINUS / "camera_intrinsics_per_view").read_text().split(), dtype=float)
    assert sinus.intrinsics[0, 2] == pytest.approx(vals[2] - 0.5) and sinus.intrinsics[1, 1] == vals[1]


def test_sinus_points_reproject_into_mask(sinus):
    uv, z = project_all(sinus.cam_from_world, sinus.intrinsics, sinus.points_xyz)
    vis = np.zeros(z.shape, bool)
    for p, v in enumerate(sinus.visibility):
        vis[v, p] = True
    assert (z[vis] > 0).all()
    assert inside_mask(uv, z, sinus.mask)[vis].mean() > 0.95
    # the inverse reading of motion.yaml (world-to-camera) would not be consistent
    T_wrong = np.linalg.inv(sinus.cam_from_world)
    uv_w, z_w = project_all(T_wrong, sinus.intrinsics, sinus.points_xyz)
    assert inside_mask(uv_w, z_w, sinus.mask)[vis].mean() < inside_mask(uv, z, sinus.mask)[vis].mean()


@pytest.mark.parametrize("binary", [True, False])
def test_sinus_colmap_round_trip(sinus, tmp_path, binary):
    out = write_colmap_model(sinus, tmp_path / "m", binary=binary)
    back = read_colmap_model(out, sinus.frame_paths, mask=sinus.mask)
    np.testing.assert_allclose(back.intrinsics, sinus.intrinsics, atol=1e-9)
    np.testing.assert_allclose(back.cam_from_world, sinus.cam_from_world, atol=1e-9)
    np.testing.assert_allclose(back.points_xyz, sinus.points_xyz, atol=1e-9)
    assert all(np.array_equal(a, b) for a, b in zip(back.visibility, sinus.visibility))


# ------------------------------------------------------------- a tiny synthetic copy, then broken
def _write_tiny(d: Path, n=3, h=24, w=32):
    d.mkdir()
    for i in range(n):
        Image.fromarray(np.full((h, w, 3), 100, np.uint8)).save(d / f"{10 + i:08d}.jpg")
    Image.fromarray(np.full((h, w), 255, np.uint8)).save(d / "undistorted_mask.bmp")
    (d / "camera_intrinsics_per_view").write_text("30\n30\n16\n12\n")
    (d / "selected_indexes").write_text("".join(f"{10 + i}\n" for i in range(n)))
    (d / "visible_view_indexes").write_text("".join(f"{10 + i}\n" for i in range(n)))
    poses = "header:\nposes[]:\n" + "".join(
        f"  poses[{i}]:\n    position:\n      x: {0.1 * i}\n      y: 0\n      z: 0\n"
        f"    orientation:\n      x: 0\n      y: 0\n      z: 0\n      w: 1\n" for i in range(n))
    (d / "motion.yaml").write_text(poses)
    (d / "structure.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                     "property float z\nend_header\n0 0 2\n0.1 0.1 3\n")
    (d / "view_indexes_per_point").write_text("-1\n10\n11\n-1\n11\n12\n")
    return d


def test_tiny_import_and_pose_convention(tmp_path):
    seq = load_original(_write_tiny(tmp_path / "t"))
    # camera-to-world position (0.1 i, 0, 0) -> cam_from_world translation -(0.1 i, 0, 0)
    np.testing.assert_allclose(seq.cam_from_world[:, :3, 3], [[0, 0, 0], [-0.1, 0, 0], [-0.2, 0, 0]], atol=1e-12)
    assert [v.tolist() for v in seq.visibility] == [[0, 1], [1, 2]]
    np.testing.assert_allclose(seq.intrinsics[:2, 2], [15.5, 11.5])


@pytest.mark.parametrize(
    "breakage, match, fname",
    [
        (lambda d: (d / "00000011.jpg").unlink(), "listed but has no image", "00000011.jpg"),
        (lambda d: (d / "00000011.jpg").write_bytes(b"not a jpeg"), "cannot read image", "00000011.jpg"),
        (lambda d: Image.fromarray(np.full((10, 10), 255, np.uint8)).save(d / "undistorted_mask.bmp"),
         "mask is 10x10", "undistorted_mask.bmp"),
        (lambda d: (d / "visible_view_indexes").write_text("10\n11\n99\n"), "pose for frame 99", "visible_view_indexes"),
        (lambda d: (d / "structure.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                                    "end_header\n"), "point cloud is empty", "structure.ply"),
        (lambda d: (d / "view_indexes_per_point").write_text("-1\n10\n-1\n77\n"), "frame 77", "view_indexes_per_point"),
        (lambda d: (d / "motion.yaml").unlink(), "pose file is missing", "motion.yaml"),
        (lambda d: (d / "camera_intrinsics_per_view").write_text("20 20 inf 12\n"), "not finite",
         "camera_intrinsics_per_view"),
        (lambda d: (d / "camera_intrinsics_per_view").write_text("20 20 nan 12\n20 20 nan 12\n"), "not finite",
         "camera_intrinsics_per_view"),
        (lambda d: Image.fromarray(np.zeros((12, 32, 3), np.uint8)).save(d / "00000012.jpg"), "frame is 32x12",
         "00000012.jpg"),
    ],
)
def test_bad_input_names_the_file(tmp_path, breakage, match, fname):
    d = _write_tiny(tmp_path / "t")
    breakage(d)
    with pytest.raises(InputError, match=match) as e:
        load_original(d)
    assert e.value.path is not None and e.value.path.name == fname


def test_frames_intrinsics_and_mask_only(tmp_path):
    """A new video in the original format has no SfM files yet: sfm=False reads what reconstruct.py needs."""
    d = _write_tiny(tmp_path / "t")
    for f in ("motion.yaml", "structure.ply", "view_indexes_per_point", "visible_view_indexes"):
        (d / f).unlink()
    with pytest.raises(InputError, match="missing"):
        load_original(d)
    seq = load_original(d, sfm=False)
    assert len(seq) == 3 and seq.mask.shape == (seq.height, seq.width)
    np.testing.assert_allclose(seq.intrinsics[:2, 2], [15.5, 11.5])

"""COLMAP model export/import: exact round trip, corner convention at the boundary, bad input."""

import numpy as np
import pytest
import torch

from endorecon.data.sequence import Sequence
from endorecon.geometry import se3_exp
from endorecon.sfm.colmap import (
    read_colmap_model,
    reconstruction_arrays,
    sequence_to_reconstruction,
    write_colmap_model,
)
from endorecon.utils.errors import InputError


def _random_sequence(n=6, p=30, seed=0):
    rng = np.random.default_rng(seed)
    T = se3_exp(torch.from_numpy(rng.normal(size=(n, 6)) * 0.2)).numpy()
    T[2] = np.nan  # an unregistered frame
    pts = rng.normal(size=(p, 3)) + [0.0, 0.0, 6.0]
    reg = [0, 1, 3, 4, 5]
    vis = [np.sort(rng.choice(reg, size=rng.integers(2, 5), replace=False)) for _ in range(p)]
    K = np.array([[55.0, 0.0, 31.25], [0.0, 57.0, 23.75], [0.0, 0.0, 1.0]])
    return Sequence("rand", [f"/nowhere/{i:04d}.png" for i in range(n)], K, 48, 64, np.ones((48, 64), bool),
                    T, pts, vis, points_rgb=rng.integers(0, 256, (p, 3)).astype(np.uint8))


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_exact(tmp_path, binary):
    seq = _random_sequence()
    out = write_colmap_model(seq, tmp_path / "model", binary=binary)
    back = read_colmap_model(out, seq.frame_paths)
    np.testing.assert_allclose(back.intrinsics, seq.intrinsics, atol=1e-12)
    assert np.isnan(back.cam_from_world[2]).all()
    reg = seq.registered
    np.testing.assert_allclose(back.cam_from_world[reg], seq.cam_from_world[reg], atol=1e-9)
    np.testing.assert_allclose(back.points_xyz, seq.points_xyz, atol=1e-9)
    assert all(np.array_equal(a, b) for a, b in zip(back.visibility, seq.visibility))
    np.testing.assert_array_equal(back.points_rgb, seq.points_rgb)
    assert (back.height, back.width) == (48, 64)


def test_corner_convention_at_the_boundary(tmp_path):
    """COLMAP's cameras.txt holds cx + 0.5, cy + 0.5; observations are projections + 0.5."""
    seq = _random_sequence()
    out = write_colmap_model(seq, tmp_path / "model", binary=False)
    cam = [ln for ln in (out / "cameras.txt").read_text().splitlines() if ln and not ln.startswith("#")][0].split()
    assert cam[1] == "PINHOLE"
    fx, fy, cx, cy = map(float, cam[4:8])
    assert (fx, fy) == (55.0, 57.0)
    assert cx == pytest.approx(31.75) and cy == pytest.approx(24.25)
    # first registered image: its 2D points are the pixel-centre projections + 0.5
    lines = [ln for ln in (out / "images.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    name = lines[0].split()[-1]
    i = int(name.split(".")[0])
    xy = np.array(lines[1].split(), dtype=float).reshape(-1, 3)[:, :2]
    ids = [p for p, v in enumerate(seq.visibility) if i in v]
    T = seq.cam_from_world[i]
    pc = seq.points_xyz[ids] @ T[:3, :3].T + T[:3, 3]
    uv = pc[:, :2] / pc[:, 2:] * [55.0, 57.0] + [31.25, 23.75]
    np.testing.assert_allclose(xy, uv + 0.5, atol=1e-6)


def test_read_bad_model(tmp_path):
    with pytest.raises(InputError, match="not a COLMAP model"):
        read_colmap_model(tmp_path, ["a.png"])
    (tmp_path / "cameras.txt").write_text("garbage\n")
    (tmp_path / "images.txt").write_text("")
    (tmp_path / "points3D.txt").write_text("")
    with pytest.raises(InputError):
        read_colmap_model(tmp_path, ["a.png"])


def test_read_model_with_other_frames(tmp_path):
    seq = _random_sequence()
    out = write_colmap_model(seq, tmp_path / "model")
    with pytest.raises(InputError, match="matches a frame"):
        read_colmap_model(out, ["/x/other.png"])


def test_an_image_the_model_holds_without_a_pose_is_an_unregistered_frame():
    """A model can keep an image whose frame lost its pose (COLMAP deregisters frames it cannot keep): its row
    is NaN and its observations are not visibility, while the other frames' poses read back."""
    seq = _random_sequence()  # frame 2 unregistered
    rec = sequence_to_reconstruction(seq)
    rec.deregister_frame(rec.images[4].frame_id)  # image ids are frame index + 1: frame 3
    assert not rec.images[4].has_pose
    out = reconstruction_arrays(rec, [f.name for f in seq.frame_paths])
    assert np.isnan(out["cam_from_world"][[2, 3]]).all()
    np.testing.assert_allclose(out["cam_from_world"][[0, 1, 4, 5]], seq.cam_from_world[[0, 1, 4, 5]], atol=1e-9)
    # (COLMAP deletes the points that are left with one observation)
    left = [[f for f in v if f != 3] for v in seq.visibility]
    assert [list(v) for v in out["visibility"]] == [v for v in left if len(v) >= 2]

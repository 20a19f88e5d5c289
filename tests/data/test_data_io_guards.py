"""Mutation guards for input readers: mask estimation, the original format's intrinsics, camera.json,
read_mask, poses.txt (endorecon.data.video / original / sequence)."""

import json

import numpy as np
import pytest
from PIL import Image

from endorecon.data import video as V
from endorecon.data.original import load_original
from endorecon.data.sequence import read_camera_json, read_mask, read_poses_txt, write_poses_txt
from endorecon.utils.errors import InputError
from test_original import _write_tiny  # tests/data/test_original.py


def _disc_frames(level=25, h=48, w=64, r=18, speck=False):
    yy, xx = np.mgrid[:h, :w]
    inside = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 <= r**2
    f = np.zeros((h, w, 3), np.uint8)
    f[inside] = level
    if speck:
        f[1:4, 1:4] = 255  # an on-screen marker in the dark border
    return [f.copy() for _ in range(3)], inside


def test_estimate_mask_keeps_dim_tissue_above_the_threshold():
    """Grey 25/255 (~0.1) is dim tissue, above the default 0.06: it is inside the mask."""
    frames, inside = _disc_frames(level=25)
    np.testing.assert_array_equal(V.estimate_mask(frames, erode=0), inside)


def test_estimate_mask_keeps_only_the_largest_region():
    frames, inside = _disc_frames(level=120, speck=True)
    m = V.estimate_mask(frames, erode=0)
    assert not m[1:4, 1:4].any()
    np.testing.assert_array_equal(m, inside)


def test_original_views_with_different_intrinsics_are_refused(tmp_path):
    d = _write_tiny(tmp_path / "t")
    (d / "camera_intrinsics_per_view").write_text("30 30 16 12\n30 30 16 12\n31 30 16 12\n")
    with pytest.raises(InputError, match="different intrinsics"):
        load_original(d)


def test_camera_json_center_origin_is_not_shifted(tmp_path):
    p = tmp_path / "camera.json"
    p.write_text(json.dumps(dict(width=64, height=48, fx=40, fy=40, cx=32, cy=24, pixel_origin="corner")))
    assert tuple(read_camera_json(p)[0][:2, 2]) == (31.5, 23.5)
    p.write_text(json.dumps(dict(width=64, height=48, fx=40, fy=40, cx=32, cy=24, pixel_origin="center")))
    assert tuple(read_camera_json(p)[0][:2, 2]) == (32.0, 24.0)


def test_read_mask_threshold_is_mid_grey(tmp_path):
    """White (> 127) is valid: a JPEG-ish dark grey border (e.g. 40) is not, light grey (200) is."""
    a = np.full((8, 8), 200, np.uint8)
    a[:, :2] = 40
    a[:, 2] = 128
    a[:, 3] = 127
    Image.fromarray(a).save(tmp_path / "m.png")
    m = read_mask(tmp_path / "m.png")
    assert not m[:, :2].any() and m[:, 2].all() and not m[:, 3].any() and m[:, 4:].all()


def test_poses_txt_reads_back_cam_from_world_not_its_inverse_or_transpose(tmp_path):
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [1.0, 2.0, 3.0]
    write_poses_txt(tmp_path / "poses.txt", ["a.png"], T[None])
    line = (tmp_path / "poses.txt").read_text().splitlines()[1].split()
    assert [float(v) for v in line[1:5]] == [0, -1, 0, 1]  # row-major, the first row with t_x
    np.testing.assert_array_equal(read_poses_txt(tmp_path / "poses.txt")[1][0], T)


def test_list_frames_skips_hidden_files(tmp_path):
    """macOS copies leave '._000.png' resource forks beside the frames: not frames."""
    from endorecon.data.sequence import list_frames

    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "000.png")
    (tmp_path / "._000.png").write_bytes(b"\x00\x05\x16\x07")
    assert [p.name for p in list_frames(tmp_path)] == ["000.png"]


def test_list_frames_takes_upper_case_suffixes(tmp_path):
    from endorecon.data.sequence import list_frames

    for k in range(2):
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / f"{k:03d}.PNG")
    assert [p.name for p in list_frames(tmp_path)] == ["000.PNG", "001.PNG"]


def test_sequence_record_of_other_frames_is_refused(tmp_path):
    from test_sequence import make_folder

    from endorecon.data.sequence import Sequence, load_sequence_folder

    d = make_folder(tmp_path)
    seq = load_sequence_folder(d)
    seq.replace(frame_paths=[p.with_name("x" + p.name) for p in seq.frame_paths]).save(d / "sequence.npz")
    with pytest.raises(InputError, match="other frames"):
        load_sequence_folder(d)

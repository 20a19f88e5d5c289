"""Mutation guards for reconstruct.py's input stage (endorecon/tasks/reconstruct.py).

Helpers come from test_reconstruct.py."""

import numpy as np
import pytest
from omegaconf import OmegaConf
from PIL import Image

from endorecon.utils.errors import InputError
from test_reconstruct import H, W, circle_frames, k_file, recon_cfg


def test_intrinsics_pixel_origin_reaches_the_text_file_reader(tmp_path):
    """(cx, cy) of a text file count from the first pixel's corner by default; intrinsics_pixel_origin=center
    takes them as given: the two must give K half a pixel apart."""
    from endorecon.tasks.reconstruct import input_sequence

    frames = circle_frames(tmp_path / "frames")
    K = k_file(tmp_path / "K.txt")
    corner = input_sequence(recon_cfg(tmp_path / "a", f"input={frames}", f"intrinsics={K}"), tmp_path / "a").intrinsics
    center = input_sequence(recon_cfg(tmp_path / "b", f"input={frames}", f"intrinsics={K}",
                                      "intrinsics_pixel_origin=center"), tmp_path / "b").intrinsics
    np.testing.assert_allclose(center[:2, 2] - corner[:2, 2], [0.5, 0.5])


def _sequence_folder(tmp_path, mask_hw):
    from endorecon.data.sequence import write_camera_json

    seq = tmp_path / "seq"
    circle_frames(seq / "frames")
    write_camera_json(seq / "camera.json", np.array([[60.0, 0, 39.5], [0, 60.0, 31.5], [0, 0, 1]]), H, W)
    Image.fromarray(np.full(mask_hw, 255, np.uint8)).save(seq / "mask.png")
    return seq


def test_a_given_mask_wins_over_the_folders_own(tmp_path):
    from endorecon.tasks.reconstruct import input_sequence

    seq = _sequence_folder(tmp_path, (H, W))
    box = np.zeros((H, W), np.uint8)
    box[8:56, 10:70] = 255
    Image.fromarray(box).save(tmp_path / "box.png")
    got = input_sequence(recon_cfg(tmp_path / "run", f"input={seq}", f"mask={tmp_path / 'box.png'}"), tmp_path / "run")
    assert (got.mask == (box > 0)).all()


def test_source_id_follows_the_frame_selection_and_the_files(tmp_path):
    from endorecon.tasks.reconstruct import _source_id

    video = tmp_path / "clip.mp4"
    video.write_bytes(b"not decoded here")
    sel = lambda **v: OmegaConf.create({"video": {"start": 0, "stride": 1, "max_frames": None, **v}})  # noqa: E731
    assert _source_id(video, sel()) == _source_id(video, sel())
    for change in ({"stride": 2}, {"start": 3}, {"max_frames": 10}):
        assert _source_id(video, sel()) != _source_id(video, sel(**change)), change
    frames = circle_frames(tmp_path / "frames")
    before = _source_id(frames, sel())
    first = sorted(frames.iterdir())[0]
    first.write_bytes(first.read_bytes() + b"\0")  # the same names, another file
    assert _source_id(frames, sel()) != before


def test_given_intrinsics_win_over_the_folders_camera(tmp_path):
    """intrinsics= is the user's correction of a folder's camera.json: it must be the K that is used."""
    from endorecon.tasks.reconstruct import input_sequence

    seq = _sequence_folder(tmp_path, (H, W))  # its camera.json: f 60, c (39.5, 31.5)
    K = tmp_path / "K.txt"
    K.write_text("70 70 40 32\n")
    own = input_sequence(recon_cfg(tmp_path / "a", f"input={seq}"), tmp_path / "a").intrinsics
    given = input_sequence(recon_cfg(tmp_path / "b", f"input={seq}", f"intrinsics={K}"), tmp_path / "b").intrinsics
    np.testing.assert_allclose(own[0, 0], 60.0)
    assert not np.allclose(given, own)
    from endorecon.data.video import read_intrinsics

    np.testing.assert_allclose(given, read_intrinsics(K, pixel_origin="corner"))

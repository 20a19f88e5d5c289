"""The Sequence record, its folder format, and consistent resizing/cropping."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from endorecon.data.sequence import (
    Sequence,
    list_frames,
    load_sequence_folder,
    read_mask,
    read_poses_txt,
    read_rgb,
    write_camera_json,
    write_poses_txt,
)
from endorecon.data.transforms import crop_sequence, downsample_and_crop_to_mask, resize_sequence
from endorecon.geometry import project, transform_points
from endorecon.utils.errors import InputError

H, W = 48, 64


def make_folder(tmp_path, n=3, h=H, w=W):
    seq = tmp_path / "seq"
    (seq / "frames").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(seq / "frames" / f"{i:04d}.png")
    yy, xx = np.mgrid[:h, :w]
    mask = ((xx - w / 2 + 0.5) ** 2 + (yy - h / 2 + 0.5) ** 2) < (0.45 * w) ** 2
    Image.fromarray(mask.astype(np.uint8) * 255).save(seq / "mask.png")
    K = np.array([[40.0, 0, (w - 1) / 2], [0, 40.0, (h - 1) / 2], [0, 0, 1]])
    write_camera_json(seq / "camera.json", K, h, w)
    return seq


def test_folder_roundtrip_and_record_save_load(tmp_path):
    seq = load_sequence_folder(make_folder(tmp_path), patient=2)
    assert len(seq) == 3 and seq.mask.shape == (H, W) and not seq.registered.any()
    assert seq.load_frame(1).shape == (H, W, 3)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[1, 0, 3] = 0.5
    seq = seq.replace(cam_from_world=poses, points_xyz=np.array([[0, 0, 2.0], [0.1, 0, 3.0]]),
                      visibility=[np.array([0, 1]), np.array([2])])
    path = seq.save(tmp_path / "rec.npz")
    back = Sequence.load(path)
    assert np.array_equal(back.cam_from_world, poses) and back.patient == 2
    assert [v.tolist() for v in back.visibility] == [[0, 1], [2]]
    assert back.frame_paths == seq.frame_paths


def test_camera_json_corner_convention_is_converted(tmp_path):
    p = tmp_path / "camera.json"
    p.write_text(json.dumps(dict(width=W, height=H, fx=40, fy=40, cx=32, cy=24, pixel_origin="corner")))
    from endorecon.data.sequence import read_camera_json

    K, h, w, _ = read_camera_json(p)
    assert (K[0, 2], K[1, 2]) == (31.5, 23.5)
    for bad in ("Corner", "top-left-corner", None):  # silently read as "center" before: half a pixel off
        p.write_text(json.dumps(dict(width=W, height=H, fx=40, fy=40, cx=32, cy=24, pixel_origin=bad)))
        with pytest.raises(InputError, match="pixel_origin") as e:
            read_camera_json(p)
        assert "camera.json" in str(e.value)


def test_bad_inputs_name_the_file(tmp_path):
    folder = make_folder(tmp_path)
    with pytest.raises(InputError, match="frame file is missing"):
        read_rgb(folder / "frames" / "9999.png")
    (folder / "frames" / "0001.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match=r"0001\.png: cannot read image"):
        load_sequence_folder(folder).load_frame(1)
    Image.fromarray(np.zeros((10, 10), np.uint8) + 255).save(folder / "mask.png")
    with pytest.raises(InputError, match=r"mask\.png: mask is 10x10 .* frames are 64x48"):
        load_sequence_folder(folder)
    Image.fromarray(np.zeros((H, W), np.uint8)).save(folder / "mask.png")
    with pytest.raises(InputError, match="no valid"):
        load_sequence_folder(folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images"):
        list_frames(tmp_path / "empty")
    with pytest.raises(InputError, match="frames directory does not exist"):
        load_sequence_folder(tmp_path / "empty")
    (folder / "camera.json").unlink()
    with pytest.raises(InputError, match="camera file is missing"):
        load_sequence_folder(folder)
    Image.fromarray(np.zeros((H + 2, W, 3), np.uint8)).save(tmp_path / "odd.png")
    with pytest.raises(InputError, match="expected 64x48"):
        read_rgb(tmp_path / "odd.png", expect_hw=(H, W))
    with pytest.raises(InputError, match="mask file is missing"):
        read_mask(tmp_path / "nope.png")


def test_poses_txt_roundtrip_with_unregistered(tmp_path):
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1] = np.nan
    write_poses_txt(tmp_path / "poses.txt", ["a.png", "b.png"], T)
    names, back = read_poses_txt(tmp_path / "poses.txt")
    assert names == ["a.png", "b.png"] and np.array_equal(back[0], T[0]) and np.isnan(back[1]).all()
    (tmp_path / "bad.txt").write_text("a.png 1 2 3\n")
    with pytest.raises(InputError, match="line 1"):
        read_poses_txt(tmp_path / "bad.txt")
    # a frames folder's names may hold spaces: reconstruct.py writes them, evaluate.py reads them back
    write_poses_txt(tmp_path / "spaces.txt", ["frame 000.png", "frame  001.png"], T)
    assert read_poses_txt(tmp_path / "spaces.txt")[0] == ["frame 000.png", "frame  001.png"]
    with pytest.raises(ValueError, match="cannot be written"):
        write_poses_txt(tmp_path / "x.txt", [" lead.png", "b.png"], T)


def _project(seq, X):
    K = torch.from_numpy(seq.intrinsics)[None]
    return project(torch.as_tensor(X, dtype=torch.float64)[None], K)[0][0].numpy()


def test_resize_and_crop_keep_points_on_their_pixels(tmp_path):
    """A world point seen at full-res pixel p lands at the resized/cropped image of p."""
    seq = load_sequence_folder(make_folder(tmp_path))
    X = np.array([[0.3, -0.2, 2.0], [-0.4, 0.25, 3.0]])
    uv = _project(seq, X)
    half = resize_sequence(seq, H // 2, W // 2)
    assert np.allclose(_project(half, X), (uv + 0.5) * 0.5 - 0.5)
    assert half.mask.shape == (H // 2, W // 2) and half.load_frame(0).shape == (H // 2, W // 2, 3)
    crop = crop_sequence(half, 4, 2, 16, 16)
    assert np.allclose(_project(crop, X), (uv + 0.5) * 0.5 - 0.5 - [4, 2])
    # The cropped frame shows the same pixels as the crop of the resized frame.
    big = np.asarray(Image.open(seq.frame_paths[0]))
    assert crop.native_window == (8, 4, 32, 32)
    ref = np.asarray(Image.fromarray(big[4:36, 8:40]).resize((16, 16), Image.BILINEAR))
    assert np.array_equal(crop.load_frame(0), ref)
    with pytest.raises(InputError, match="outside"):
        crop_sequence(half, 20, 0, 16, 16)
    # a resize by 3/4 then a crop at a third of a native pixel: the frames would be cut 1/3 px off K
    three_q = resize_sequence(seq, H * 3 // 4, W * 3 // 4)
    with pytest.raises(InputError, match="not whole pixels"):
        crop_sequence(three_q, 1, 0, 6, 6)
    assert crop_sequence(three_q, 3, 3, 6, 6).native_window == (4, 4, 8, 8)


def test_original_method_preprocessing_crops_to_multiple_of_64(tmp_path):
    seq = load_sequence_folder(make_folder(tmp_path, n=1, h=540, w=960))
    small = downsample_and_crop_to_mask(seq, factor=2, multiple=64)
    assert small.height % 64 == 0 and small.width % 64 == 0
    odd = load_sequence_folder(make_folder(tmp_path / "odd", n=1, h=541, w=963))  # sides not multiples of 2
    assert downsample_and_crop_to_mask(odd, factor=2, multiple=64).height % 64 == 0
    assert small.load_frame(0).shape == (small.height, small.width, 3)


def test_unregistered_rows_and_shape_checks(tmp_path):
    seq = load_sequence_folder(make_folder(tmp_path))
    with pytest.raises(InputError, match="cam_from_world must be"):
        seq.replace(cam_from_world=np.zeros((2, 4, 4)))
    with pytest.raises(InputError, match="visibility"):
        seq.replace(points_xyz=np.zeros((2, 3)), visibility=[np.array([0])])
    T = np.tile(np.eye(4), (3, 1, 1))
    T[2] = np.nan
    assert seq.replace(cam_from_world=T).registered.tolist() == [True, True, False]
    X = transform_points(torch.eye(4, dtype=torch.float64)[None], torch.zeros(1, 1, 3, dtype=torch.float64))
    assert X.shape == (1, 1, 3)


def test_sfm_fingerprint_and_fixed_frame_tell_sfm_models_apart():
    from endorecon.data.sequence import same_fixed_frame, sfm_fingerprint

    K = np.array([[50.0, 0, 39.5], [0, 50.0, 31.5], [0, 0, 1]])
    pts = np.arange(30, dtype=np.float64).reshape(10, 3)
    poses = np.tile(np.eye(4), (3, 1, 1))
    seq = Sequence("p/s", [f"{i}.png" for i in range(3)], K, 64, 80, np.ones((64, 80), bool), poses, pts,
                   [np.arange(3)] * 10)
    assert sfm_fingerprint(seq) == sfm_fingerprint(seq.replace(cam_from_world=poses * 2))  # poses do not count
    assert sfm_fingerprint(seq) != sfm_fingerprint(seq.replace(points_xyz=pts + 1e-9))
    assert sfm_fingerprint(seq.replace(points_xyz=None, visibility=None)) is None
    refined = poses.copy()
    refined[1:, 0, 3] += 0.01  # PGO moves the others, never the first registered frame
    assert same_fixed_frame(poses, refined) is True
    refined[0, 0, 3] += 1e-3
    assert same_fixed_frame(poses, refined) is False
    unreg = poses.copy()
    unreg[0] = np.nan  # the first registered frame is then frame 1
    assert same_fixed_frame(unreg, np.concatenate([refined[:1], poses[1:]])) is True
    assert same_fixed_frame(poses, poses[:2]) is None


def test_list_frames_orders_numbers_by_value(tmp_path):
    for k in (1, 2, 10, 11, 3):
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / f"frame_{k}.png")
    assert [p.name for p in list_frames(tmp_path)] == [f"frame_{k}.png" for k in (1, 2, 3, 10, 11)]


def test_artifacts_get_the_permissions_of_a_plain_write(tmp_path):
    import os

    from endorecon.utils.io import atomic_dir, atomic_write_text

    old = os.umask(0o022)
    try:
        f = atomic_write_text(tmp_path / "a.txt", "x")
        with atomic_dir(tmp_path / "d") as tmp:
            (tmp / "b").write_text("y")
    finally:
        os.umask(old)
    assert f.stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o755


def test_damaged_sequence_record_is_an_input_error(tmp_path):
    path = tmp_path / "sequence.npz"
    path.write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(InputError, match="corrupt sequence record") as e:
        Sequence.load(path)
    assert e.value.path == path


def test_remove_path_file_dir_link_and_missing(tmp_path):
    from endorecon.utils.io import remove_path

    (tmp_path / "d" / "sub").mkdir(parents=True)
    (tmp_path / "d" / "sub" / "x.txt").write_text("x")
    (tmp_path / "f.txt").write_text("f")
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "y.txt").write_text("y")
    (tmp_path / "link").symlink_to(tmp_path / "kept")
    for name in ["d", "f.txt", "link", "missing"]:
        remove_path(tmp_path / name)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"]
    # a link to a folder is removed, not the folder it points to
    assert (tmp_path / "kept" / "y.txt").read_text() == "y"

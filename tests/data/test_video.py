"""Video decoding, intrinsics files, mask estimation and the texture check (endorecon.data.video)."""

import json
import subprocess

import numpy as np
import pytest
from PIL import Image

from endorecon.data import video as V
from endorecon.utils.errors import InputError

ffmpeg_mod = pytest.importorskip("imageio_ffmpeg")
H, W = 64, 80


def textured_frames(n: int, seed: int = 0) -> list[np.ndarray]:
    """Smooth random texture translating by 2 px a frame (codec-friendly, clearly different frames)."""
    rng = np.random.default_rng(seed)
    big = rng.random((H // 4 + 8, (W + 2 * n) // 4 + 8, 3))
    big = np.asarray(Image.fromarray((big * 255).astype(np.uint8)).resize(((W + 2 * n) + 32, H + 32), Image.BICUBIC))
    return [np.ascontiguousarray(big[8 : 8 + H, 2 * k : 2 * k + W]) for k in range(n)]


def write_video(path, frames, faststart: bool = True, codec: str = "libx264"):
    """Encode frames with the imageio-ffmpeg binary (a real encoder, as a user's file would be)."""
    src = path.parent / f".{path.stem}_src"
    src.mkdir(exist_ok=True)
    for k, f in enumerate(frames):
        Image.fromarray(f).save(src / f"{k:04d}.png")
    cmd = [ffmpeg_mod.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-framerate", "10", "-i", str(src / "%04d.png"),
           "-c:v", codec]
    if codec == "libx264":
        cmd += ["-pix_fmt", "yuv444p", "-crf", "10", "-g", "4"]
    if faststart:
        cmd += ["-movflags", "+faststart"]
    subprocess.run(cmd + [str(path)], check=True)
    return path


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("video")
    frames = textured_frames(12)
    return write_video(d / "clip.mp4", frames), frames


def test_extract_frames_decodes_every_frame(clip, tmp_path):
    path, frames = clip
    out = V.extract_frames(path, tmp_path / "frames")
    assert len(out) == len(frames)
    for p, ref in zip(out, frames):
        got = np.asarray(Image.open(p))
        assert got.shape == (H, W, 3)
        assert np.abs(got.astype(float) - ref).mean() < 4.0  # near-lossless encode
    meta = json.loads((tmp_path / "frames" / "decode.json").read_text())
    assert meta["decoded"] == 12 and meta["expected"] == 12 and not meta["truncated"]


def test_extract_frames_stride_start_max(clip, tmp_path):
    path, frames = clip
    out = V.extract_frames(path, tmp_path / "f", stride=3, start=1, max_frames=3)
    assert len(out) == 3
    # frames 1, 4, 7 of the clip
    for p, k in zip(out, (1, 4, 7)):
        got = np.asarray(Image.open(p)).astype(float)
        errs = [np.abs(got - f).mean() for f in frames]
        assert int(np.argmin(errs)) == k


def test_extract_frames_is_resumable(clip, tmp_path, monkeypatch):
    path, _ = clip
    first = V.extract_frames(path, tmp_path / "frames")

    def no_decoder():
        raise AssertionError("decoded again")

    monkeypatch.setattr(V, "_decoder", no_decoder)
    assert V.extract_frames(path, tmp_path / "frames") == first
    # another selection, or another video in the same folder (a run stopped before recording its input):
    # decoded again, not the first one's frames handed back
    monkeypatch.undo()
    assert len(V.extract_frames(path, tmp_path / "frames", stride=2)) == 6
    other = write_video(tmp_path / "other.mp4", textured_frames(5, seed=3))
    got = V.extract_frames(other, tmp_path / "frames")
    assert len(got) == 5 and json.loads((tmp_path / "frames" / "decode.json").read_text())["video"] == str(other)


def test_audio_longer_than_the_video_is_not_truncation(clip, tmp_path):
    """The header's duration is the container's: a 1.2 s video with 3 s of audio is complete (it was refused
    as truncated: 12 of the 30 frames the duration announced)."""
    path, _ = clip
    both = tmp_path / "with_audio.mp4"
    subprocess.run([ffmpeg_mod.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-i", str(path), "-f", "lavfi", "-i",
                    "sine=duration=3", "-c:v", "copy", "-c:a", "aac", str(both)],
                   check=True)
    out = V.extract_frames(both, tmp_path / "frames")
    meta = json.loads((tmp_path / "frames" / "decode.json").read_text())
    assert len(out) == 12 and not meta["truncated"] and meta["audio"] and meta["expected"] > 12


def test_unreadable_video(tmp_path):
    bad = tmp_path / "junk.mp4"
    bad.write_bytes(np.random.default_rng(0).bytes(3000))
    with pytest.raises(InputError) as e:
        V.extract_frames(bad, tmp_path / "frames")
    assert e.value.path == bad and "decode" in str(e.value) and e.value.fix
    assert not (tmp_path / "frames").exists()  # nothing half-written


def test_missing_video(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        V.extract_frames(tmp_path / "nope.mp4", tmp_path / "frames")


def test_truncated_video(clip, tmp_path):
    path, _ = clip
    data = path.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: len(data) * 6 // 10])
    with pytest.raises(InputError, match="truncated") as e:
        V.extract_frames(cut, tmp_path / "frames")
    assert e.value.path == cut and "allow_truncated" in e.value.fix
    assert not (tmp_path / "frames").exists()
    out = V.extract_frames(cut, tmp_path / "frames", allow_truncated=True)
    meta = json.loads((tmp_path / "frames" / "decode.json").read_text())
    assert 3 <= len(out) < 12 and meta["truncated"] and meta["decoded"] == len(out)


def test_truncated_avi_is_detected(tmp_path):
    # a cut AVI has no index: ffmpeg estimates its duration from the size, the header still counts every frame
    path = write_video(tmp_path / "clip.avi", textured_frames(20), faststart=False, codec="mjpeg")
    assert V.avi_declared_frames(path) == 20 and V.avi_declared_frames(tmp_path / "none.avi") is None
    cut = tmp_path / "cut.avi"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 85 // 100])
    with pytest.raises(InputError, match="truncated") as e:
        V.extract_frames(cut, tmp_path / "frames")
    assert "of the 20 its header announces" in str(e.value)
    assert len(V.extract_frames(path, tmp_path / "full")) == 20


def test_truncated_without_index_is_unreadable(tmp_path):
    # without faststart the index (moov) sits at the end: a cut file cannot be opened at all
    path = write_video(tmp_path / "slow.mp4", textured_frames(12), faststart=False)
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(InputError, match="decode"):
        V.extract_frames(cut, tmp_path / "frames")


def test_too_short_video(tmp_path):
    path = write_video(tmp_path / "two.mp4", textured_frames(2))
    with pytest.raises(InputError, match="at least 3") as e:
        V.extract_frames(path, tmp_path / "frames")
    assert "re-encode" in e.value.fix


@pytest.mark.parametrize("selection", [dict(max_frames=2), dict(start=10), dict(stride=6)])
def test_frame_selection_leaving_too_few_frames_names_the_selection(clip, tmp_path, selection):
    """A 12-frame clip cut to < 3 frames by video.start / stride / max_frames: the fix was to re-encode the file."""
    path, _ = clip
    with pytest.raises(InputError, match="frame selection keeps") as e:
        V.extract_frames(path, tmp_path / "frames", **selection)
    assert "video.start" in e.value.fix and not (tmp_path / "frames").exists()


# ------------------------------------------------------------------ intrinsics
def test_read_intrinsics_conventions(tmp_path):
    f = tmp_path / "K.txt"
    f.write_text("# fx fy cx cy\n100 110 40 32\n")
    Kc = V.read_intrinsics(f, "corner")
    Kp = V.read_intrinsics(f, "center")
    assert Kc[0, 0] == 100 and Kc[1, 1] == 110
    assert (Kc[0, 2], Kc[1, 2]) == (39.5, 31.5)
    assert (Kp[0, 2], Kp[1, 2]) == (40.0, 32.0)


@pytest.mark.parametrize("text", ["", "100 110 40\n", "a b c d\n", "-1 100 40 32\n", "nan 1 2 3\n"])
def test_read_intrinsics_bad(tmp_path, text):
    f = tmp_path / "K.txt"
    f.write_text(text)
    with pytest.raises(InputError) as e:
        V.read_intrinsics(f)
    assert e.value.path == f


def test_read_intrinsics_of_the_original_method(tmp_path):
    """camera_intrinsics_per_view holds fx, fy, cx, cy one a line (corner convention): it was refused."""
    f = tmp_path / "camera_intrinsics_per_view"
    f.write_text("677.171\n677.171\n872.127\n471.918\n")
    K = V.read_intrinsics(f, "corner")
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == (677.171, 677.171, 871.627, 471.418)
    f.write_text("677.171\n677.171\n872.127\n")
    with pytest.raises(InputError):
        V.read_intrinsics(f)


def test_read_intrinsics_missing(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        V.read_intrinsics(tmp_path / "none.txt")


def test_principal_point_outside_frames():
    K = np.array([[100, 0, 959.5], [0, 100, 539.5], [0, 0, 1.0]])
    V.check_intrinsics_fit(K, 1080, 1920)
    with pytest.raises(InputError, match="another resolution"):
        V.check_intrinsics_fit(K, 64, 80)


def test_intrinsics_for_twice_the_resolution_are_refused():
    # the sinus clip's camera: its own 1920x1080 frames pass, the frames at half size do not (cx still inside)
    K = np.array([[677.2, 0, 871.6], [0, 677.2, 471.4], [0, 0, 1.0]])
    V.check_intrinsics_fit(K, 1080, 1920)
    V.check_intrinsics_fit(K * np.array([[0.5], [0.5], [1.0]]) + np.array([[0, 0, -0.25], [0, 0, -0.25], [0, 0, 0]]),
                           540, 960)
    assert 0 <= K[0, 2] < 960 and 0 <= K[1, 2] < 540
    with pytest.raises(InputError, match="another resolution") as e:
        V.check_intrinsics_fit(K, 540, 960, "K.txt")
    assert "960x540" in e.value.fix


# ------------------------------------------------------------------ mask and texture
def _circle_frames(n=4, r=25):
    yy, xx = np.mgrid[:H, :W]
    inside = (yy - 31.5) ** 2 + (xx - 39.5) ** 2 < r**2
    frames = []
    for f in textured_frames(n):
        g = (0.3 * 255 + 0.5 * f).astype(np.uint8)
        g[~inside] = 3  # dark border with a little noise floor
        frames.append(g)
    return frames, inside


def test_estimate_mask_finds_the_circle():
    frames, inside = _circle_frames()
    m = V.estimate_mask(frames, erode=0)
    assert (m == inside).mean() > 0.99
    m3 = V.estimate_mask(frames, erode=3)
    assert m3.sum() < m.sum() and not (m3 & ~inside).any()


def test_estimate_mask_black_frames():
    with pytest.raises(InputError, match="black"):
        V.estimate_mask([np.zeros((H, W, 3), np.uint8)] * 3)


def test_texture_check():
    frames, inside = _circle_frames()
    assert V.check_texture(frames, inside) > 5
    flat = [np.full((H, W, 3), 120, np.uint8)] * 3
    with pytest.raises(InputError, match="no texture"):
        V.check_texture(flat, inside)
    assert V.texture_level(flat[0], inside) == 0.0

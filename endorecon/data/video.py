"""Inputs of the application phase: frames from a video file, intrinsics files, mask estimation."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from endorecon.data.sequence import list_frames, read_camera_json
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_dir, atomic_write_text

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".mpg", ".mpeg", ".m4v", ".wmv")


def extract_frames(video: str | Path, out_dir: str | Path, stride: int = 1, max_frames: int | None = None,
                   start: int = 0) -> list[Path]:
    """Decode a video (ffmpeg via imageio) into ``out_dir/000000.png ...``; skips if already complete.

    A truncated or unreadable video is an :class:`InputError`; frames decoded
    before a mid-stream error are kept only if at least two were read (and
    the error is reported in ``out_dir/decode.json``).
    """
    import imageio.v3 as iio
    from PIL import Image

    video, out_dir = Path(video), Path(out_dir)
    if (out_dir / "decode.json").is_file():
        return list_frames(out_dir)
    if not video.is_file():
        raise InputError("video file does not exist", video, "pass input=<video file or frames folder>")
    n_read, error = 0, None
    with atomic_dir(out_dir) as tmp:
        try:
            for k, frame in enumerate(iio.imiter(video, plugin="pyav") if _has_pyav() else iio.imiter(video)):
                if k < start or (k - start) % stride:
                    continue
                arr = np.asarray(frame)
                if arr.ndim == 2:
                    arr = np.stack([arr] * 3, -1)
                Image.fromarray(arr[..., :3]).save(tmp / f"{n_read:06d}.png")
                n_read += 1
                if max_frames is not None and n_read >= max_frames:
                    break
        except Exception as e:  # decoders raise many kinds; what matters is what was read
            error = f"{type(e).__name__}: {e}"
        if n_read < 2:
            raise InputError(
                f"could not decode the video ({error or 'fewer than 2 frames'})",
                video,
                "check the file (ffprobe), or extract frames yourself and pass the folder",
            )
        atomic_write_text(tmp / "decode.json", json.dumps(dict(video=str(video), frames=n_read, stride=stride,
                                                              error=error)) + "\n")
    return list_frames(out_dir)


def _has_pyav() -> bool:
    try:
        import av  # noqa: F401

        return True
    except ImportError:
        return False


def read_intrinsics(path: str | Path, pixel_origin: str = "corner") -> np.ndarray:
    """Intrinsics from ``camera.json`` or a text file whose first line is ``fx fy cx cy``.

    Text files carry no convention: ``pixel_origin`` says whether (cx, cy) count
    from the top-left pixel's corner (COLMAP, the original method) or centre.
    Returns K (3, 3) in the pixel-centre convention.
    """
    path = Path(path)
    if path.suffix == ".json":
        return read_camera_json(path)[0]
    if not path.is_file():
        raise InputError("intrinsics file does not exist", path, "pass intrinsics=<camera.json or fx fy cx cy file>")
    try:
        first = next(ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#"))
        fx, fy, cx, cy = (float(v) for v in first.replace(",", " ").split()[:4])
    except (StopIteration, ValueError) as e:
        raise InputError("expected a first line 'fx fy cx cy'", path) from e
    shift = 0.5 if pixel_origin == "corner" else 0.0
    K = np.array([[fx, 0, cx - shift], [0, fy, cy - shift], [0, 0, 1]], dtype=np.float64)
    if not np.isfinite(K).all() or fx <= 0 or fy <= 0:
        raise InputError("intrinsics are not finite and positive", path)
    return K


def estimate_mask(frames: list[np.ndarray], threshold: float = 0.06, erode: int = 3) -> np.ndarray:
    """Valid-pixel mask from the dark border of endoscopic frames.

    A pixel is valid when its brightness over the frames (90th percentile) is
    above ``threshold`` (grey in [0, 1]); the largest connected region is kept,
    its holes filled, and the rim eroded by ``erode`` pixels.
    """
    from scipy import ndimage

    if not frames:
        raise InputError("no frames to estimate a mask from")
    grey = np.stack([f.astype(np.float32).mean(-1) / 255.0 for f in frames])
    bright = np.percentile(grey, 90, axis=0) > threshold
    lab, n = ndimage.label(bright)
    if n == 0:
        raise InputError("the frames are black: no valid pixel found for a mask", fix="pass mask=<png> (white = valid)")
    sizes = ndimage.sum(bright, lab, index=np.arange(1, n + 1))
    mask = ndimage.binary_fill_holes(lab == (1 + int(np.argmax(sizes))))
    if erode > 0:
        mask = ndimage.binary_erosion(mask, iterations=erode)
    if mask.mean() < 0.05:
        raise InputError(f"estimated mask covers only {mask.mean():.1%} of the image",
                         fix="pass mask=<png> (white = valid)")
    return mask

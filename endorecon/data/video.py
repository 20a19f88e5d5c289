"""Inputs of the application phase: frames from a video file, intrinsics files, mask estimation, texture check.

* :func:`extract_frames` — decode a video (ffmpeg, via the ``imageio-ffmpeg`` binary) into PNG frames; a
  truncated or unreadable file is an :class:`InputError`.
* :func:`read_intrinsics` — K from ``camera.json`` or a plain ``fx fy cx cy`` text file.
* :func:`estimate_mask` — the endoscope's field of view from the dark border of the frames.
* :func:`check_texture` — refuse frames with nothing for SfM to match (black, constant), before SfM runs.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from endorecon.data.sequence import list_frames, read_camera_json
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_dir, atomic_write_text, file_id

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".mpg", ".mpeg", ".m4v", ".wmv")


def _decoder():
    try:
        import imageio_ffmpeg
    except ImportError as e:  # an optional dependency (pyproject extra "video")
        raise InputError("reading a video needs the imageio-ffmpeg package", fix="pip install imageio-ffmpeg, "
                         "or extract the frames yourself and pass the folder") from e
    return imageio_ffmpeg


def extract_frames(video: str | Path, out_dir: str | Path, stride: int = 1, max_frames: int | None = None,
                   start: int = 0, allow_truncated: bool = False) -> list[Path]:
    """Decode a video into ``out_dir/000000.png ...``; skipped if ``out_dir/decode.json`` exists (complete).

    Frames ``start, start + stride, ...`` are kept, at most ``max_frames``.  The
    folder appears only when complete (atomic).  Errors (:class:`InputError`):
    a missing or undecodable file; fewer than 3 frames; a *truncated* file —
    fewer frames decoded than its header's duration x fps announces — unless
    ``allow_truncated`` (then the decoded frames are used and ``decode.json``
    says so).
    """
    from PIL import Image
    from rich.progress import Progress

    video, out_dir = Path(video), Path(out_dir)
    request = dict(source=file_id(video) if video.is_file() else None, start=start, stride=stride,
                   max_frames=max_frames)
    if (out_dir / "decode.json").is_file():
        try:
            done = json.loads((out_dir / "decode.json").read_text())
        except (OSError, ValueError):
            done = {}
        if all(done.get(k) == v for k, v in request.items()):
            return list_frames(out_dir)
        # another video or frame selection (a run stopped before it recorded its input), or a record from
        # before the request was kept: decode again, replacing the folder as a whole
        log.info("%s holds frames of another video or selection: decoding %s again", out_dir, video)
    if not video.is_file():
        raise InputError("video file does not exist", video, "pass input=<video file or frames folder>")
    if stride < 1 or start < 0 or (max_frames is not None and max_frames < 1):
        raise InputError(f"bad frame selection stride={stride} start={start} max_frames={max_frames}",
                         fix="video.stride >= 1, video.start >= 0, video.max_frames >= 1 or null")
    ffmpeg = _decoder()
    fix = "check the file (ffprobe), re-encode it (ffmpeg -i in.mp4 -c:v libx264 out.mp4), or extract the frames " \
          "yourself and pass the folder"
    decoded = kept = 0
    error = None
    with atomic_dir(out_dir) as tmp:
        try:
            gen = ffmpeg.read_frames(str(video), pix_fmt="rgb24")
            meta = next(gen)
        except Exception as e:  # ffmpeg reports unreadable files as OSError/RuntimeError/StopIteration
            raise InputError(f"cannot decode the video ({_short(e)})", video, fix) from e
        w, h = (int(v) for v in meta["size"])
        fps, duration = float(meta.get("fps") or 0), float(meta.get("duration") or 0)
        expected = int(round(fps * duration)) if fps > 0 and duration > 0 else None
        # the header's duration is the container's: with an audio track it may be the audio's, longer than the
        # video (a complete file was refused as truncated); then a shortfall is only a warning
        audio = bool(meta.get("audio_codec"))
        declared = avi_declared_frames(video)
        if declared:  # an AVI without its index reports a duration estimated from the file size: not a check
            expected = declared
        stopped_early = False
        with Progress(transient=True) as bar:
            task = bar.add_task(f"decode {video.name}", total=expected)
            try:
                for raw in gen:
                    if len(raw) != w * h * 3:
                        raise OSError(f"frame {decoded} has {len(raw)} bytes, expected {w * h * 3}")
                    if decoded >= start and (decoded - start) % stride == 0:
                        arr = np.frombuffer(raw, np.uint8).reshape(h, w, 3)
                        Image.fromarray(arr).save(tmp / f"{kept:06d}.png")
                        kept += 1
                    decoded += 1
                    bar.advance(task)
                    if max_frames is not None and kept >= max_frames:
                        stopped_early = True
                        break
            except Exception as e:  # a decoder error mid-stream: judged below with what was read
                error = _short(e)
            finally:
                gen.close()
        # Truncation: ffmpeg stops quietly at the end of the data; the header still announces the full length.
        # (Containers round duration x fps: allow 5 % + 1 frame of slack.)
        short = not stopped_early and expected is not None and decoded < 0.95 * expected - 1
        truncated = not stopped_early and (error is not None or (short and not audio))
        if short and audio and error is None:
            log.warning("%s: %d frames decoded, the container's duration (%.2f s, audio included) allows %d: the "
                        "audio track may be longer than the video, or the video is cut", video, decoded, duration,
                        expected)
        what = f"decoded {decoded} frame(s)" + (f" of the {expected} its header announces" if expected else "") \
            + (f"; decoder error: {error}" if error else "")
        if kept < 3 and (stopped_early or decoded >= 3):  # the file had frames: the selection left too few
            raise InputError(f"the frame selection keeps {kept} of the video's frames (start={start}, stride="
                             f"{stride}, max_frames={max_frames}; {what}); SfM needs at least 3", video,
                             "lower video.start / video.stride, or raise video.max_frames (>= 3)")
        if kept < 3:
            raise InputError(f"video gave only {kept} usable frame(s), SfM needs at least 3 ({what})", video, fix)
        if truncated and not allow_truncated:
            raise InputError(f"video looks truncated: {what}", video,
                             f"{fix}; or pass video.allow_truncated=true to reconstruct the {kept} decoded frames")
        if truncated:
            log.warning("%s: truncated video, using the %d decoded frames (%s)", video, kept, what)
        atomic_write_text(tmp / "decode.json", json.dumps(dict(
            video=str(video), size=[h, w], fps=fps, duration_s=duration, expected=expected, decoded=decoded,
            frames=kept, start=start, stride=stride, truncated=truncated, error=error, audio=audio,
            source=request["source"], max_frames=max_frames), indent=2) + "\n")
    return list_frames(out_dir)


def avi_declared_frames(path: str | Path) -> int | None:
    """The frame count an AVI's main header (``avih``, dwTotalFrames) declares; None for other files.

    ffmpeg reports a cut AVI's duration from its size, so "decoded < duration x fps" misses truncation
    there; the header, written when the file was closed, still holds the full count."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return None
    if head[:4] != b"RIFF" or head[8:12] != b"AVI ":
        return None
    i = head.find(b"avih")
    if i < 0 or len(head) < i + 28:
        return None
    total = int.from_bytes(head[i + 24 : i + 28], "little")  # the fifth uint32 of the header's data
    return total or None


def _short(e: BaseException) -> str:
    # ffmpeg's messages carry the whole build banner: keep the first meaningful line
    msg = str(e).strip().splitlines()
    return f"{type(e).__name__}: {msg[0][:200] if msg else ''}"


def read_intrinsics(path: str | Path, pixel_origin: str = "corner") -> np.ndarray:
    """Intrinsics from ``camera.json``, a text file whose first line is ``fx fy cx cy``, or the original
    method's ``camera_intrinsics_per_view`` (fx, fy, cx, cy one a line).

    Text files carry no convention: ``pixel_origin`` says whether (cx, cy) count
    from the top-left pixel's corner (COLMAP, the original method) or centre.
    Returns K (3, 3) in the pixel-centre convention.
    """
    path = Path(path)
    if pixel_origin not in ("corner", "center"):
        raise InputError(f"intrinsics_pixel_origin must be 'corner' or 'center', got {pixel_origin!r}")
    if not path.is_file():
        raise InputError("intrinsics file does not exist", path,
                         "pass intrinsics=<camera.json or a text file 'fx fy cx cy'>")
    if path.suffix == ".json":
        return read_camera_json(path)[0]
    try:
        lines = [ln.replace(",", " ").split() for ln in path.read_text().splitlines()
                 if ln.strip() and not ln.lstrip().startswith("#")]
        if not lines:
            raise ValueError("no numbers")
        if len(lines[0]) == 1 and len(lines) >= 4 and all(len(ln) == 1 for ln in lines[:4]):
            vals = [float(ln[0]) for ln in lines[:4]]  # the original method's file: fx, fy, cx, cy one a line
        else:
            vals = [float(v) for v in lines[0]]
        if len(vals) < 4:
            raise ValueError(f"{len(vals)} numbers")
        fx, fy, cx, cy = vals[:4]
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"expected a first line 'fx fy cx cy', or fx, fy, cx, cy one a line ({e})", path,
                         "write fx fy cx cy in pixels") from e
    shift = 0.5 if pixel_origin == "corner" else 0.0
    K = np.array([[fx, 0, cx - shift], [0, fy, cy - shift], [0, 0, 1]], dtype=np.float64)
    if not np.isfinite(K).all() or fx <= 0 or fy <= 0:
        raise InputError("intrinsics are not finite and positive", path, "write fx fy cx cy in pixels")
    return K


# How far from the image centre the principal point may lie, as a fraction of each side.  Endoscopes put it
# near the centre (the sinus clip: 5 % off); a K for twice the resolution puts it ~0.4-0.5 of a side off.
MAX_PRINCIPAL_OFFSET = 0.25


def check_intrinsics_fit(K: np.ndarray, height: int, width: int, path: str | Path | None = None) -> None:
    """The principal point must lie near the frames' centre (pixel-centre K): a K for another resolution
    is the usual mistake, and one for twice the resolution still puts (cx, cy) inside the frames."""
    cx, cy = K[0, 2], K[1, 2]
    off_x, off_y = abs(cx - (width - 1) / 2) / width, abs(cy - (height - 1) / 2) / height
    if not (0 <= cx < width and 0 <= cy < height) or max(off_x, off_y) > MAX_PRINCIPAL_OFFSET:
        raise InputError(f"principal point ({cx:.1f}, {cy:.1f}) is {max(off_x, off_y):.0%} of the frame off the "
                         f"centre of the {width}x{height} frames (at most {MAX_PRINCIPAL_OFFSET:.0%} expected): the "
                         "intrinsics are probably for another resolution", path,
                         f"give fx fy cx cy in pixels of the {width}x{height} frames (scale them by the resize)")


def estimate_mask(frames: list[np.ndarray], threshold: float = 0.06, erode: int = 3) -> np.ndarray:
    """Valid-pixel mask from the dark border of endoscopic frames.

    Args:
        frames: a few (H, W, 3) uint8 frames.
    Returns:
        (H, W) bool: pixels whose brightness over the frames (90th percentile,
        grey in [0, 1]) is above ``threshold``; the largest connected region,
        holes filled, rim eroded by ``erode`` pixels.
    """
    from scipy import ndimage

    if not frames:
        raise InputError("no frames to estimate a mask from")
    grey = np.stack([f.astype(np.float32).mean(-1) / 255.0 for f in frames])
    bright = np.percentile(grey, 90, axis=0) > threshold
    lab, n = ndimage.label(bright)
    if n == 0:
        raise InputError("the frames are black: no valid pixel for a mask (and nothing for SfM to match)",
                         fix="check the video, or pass mask=<png> (white = valid)")
    sizes = ndimage.sum(bright, lab, index=np.arange(1, n + 1))
    mask = ndimage.binary_fill_holes(lab == (1 + int(np.argmax(sizes))))
    if erode > 0:
        mask = ndimage.binary_erosion(mask, iterations=erode, border_value=1)
    if mask.mean() < 0.05:
        raise InputError(f"estimated mask covers only {mask.mean():.1%} of the image",
                         fix="pass mask=<png> (white = valid)")
    return mask


def texture_level(frame: np.ndarray, mask: np.ndarray) -> float:
    """Mean grey-level gradient magnitude (in 1/255 units per pixel) inside ``mask``.

    frame: (H, W, 3) uint8; mask: (H, W) bool.
    """
    g = frame.astype(np.float32).mean(-1)
    gx = np.abs(np.diff(g, axis=1))[:-1, :]
    gy = np.abs(np.diff(g, axis=0))[:, :-1]
    m = mask[:-1, :-1] & mask[1:, :-1] & mask[:-1, 1:]
    if not m.any():
        return 0.0
    return float((gx + gy)[m].mean())


def check_texture(frames: list[np.ndarray], mask: np.ndarray, min_level: float = 0.5,
                  path: str | Path | None = None) -> float:
    """Raise if the frames show no texture (black, constant or blank frames: SfM would find nothing).

    Returns the median :func:`texture_level` over ``frames``.  ``min_level`` is in
    grey levels per pixel: rendered phantoms and real endoscopy sit far above it.
    """
    levels = [texture_level(f, mask) for f in frames]
    med = float(np.median(levels)) if levels else 0.0
    if med < min_level:
        raise InputError(f"the frames show no texture (mean gradient {med:.2f} grey levels/pixel < {min_level}): "
                         "black, constant or blank frames give SfM nothing to match", path,
                         "check the video/frames (and the mask), or lower input_checks.min_texture")
    return med

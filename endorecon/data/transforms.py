"""Resizing and cropping a whole sequence consistently.

Intrinsics, mask and the frame window change together; sparse points are 3D
world points and need no change.  Frames are resized when loaded
(:meth:`Sequence.load_frame`), so no image is rewritten on disk.
"""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from endorecon.data.sequence import Sequence
from endorecon.geometry import crop_intrinsics, mask_bbox_crop, scale_intrinsics
from endorecon.utils.errors import InputError


def _window(seq: Sequence) -> tuple[int, int, int, int]:
    return seq.native_window if seq.native_window is not None else (0, 0, seq.width, seq.height)


def _resize_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    # Area-average then keep pixels that are mostly valid: the rim stays conservative.
    img = Image.fromarray(mask.astype(np.uint8) * 255).resize((width, height), Image.BOX)
    return np.asarray(img) > 200


def resize_sequence(seq: Sequence, height: int, width: int) -> Sequence:
    """The same sequence seen at (height, width): K scaled (pixel-centre rule), mask resized."""
    if height <= 0 or width <= 0:
        raise InputError(f"cannot resize to {width}x{height}")
    sx, sy = width / seq.width, height / seq.height
    K = scale_intrinsics(torch.from_numpy(seq.intrinsics)[None], sx, sy)[0].numpy()
    return seq.replace(
        intrinsics=K,
        height=height,
        width=width,
        mask=_resize_mask(seq.mask, height, width),
        native_window=_window(seq) if seq.native_window is not None or (height, width) != (seq.height, seq.width) else None,
    )


def crop_sequence(seq: Sequence, x0: int, y0: int, width: int, height: int) -> Sequence:
    """The sequence restricted to the window (x0, y0, width, height) of its current frames."""
    if x0 < 0 or y0 < 0 or x0 + width > seq.width or y0 + height > seq.height:
        raise InputError(f"crop window {(x0, y0, width, height)} is outside the {seq.width}x{seq.height} frames")
    K = crop_intrinsics(torch.from_numpy(seq.intrinsics)[None], x0, y0)[0].numpy()
    wx0, wy0, ww, wh = _window(seq)
    fx, fy = ww / seq.width, wh / seq.height  # native pixels per current pixel
    exact = (wx0 + x0 * fx, wy0 + y0 * fy, width * fx, height * fy)
    window = tuple(int(round(v)) for v in exact)
    # the frames are cut at whole native pixels: a window that is not would put them up to half a pixel off K
    if max(abs(a - b) for a, b in zip(exact, window)) > 1e-6:
        raise InputError(f"crop window {(x0, y0, width, height)} of this resized sequence is the native window "
                         f"{tuple(round(v, 3) for v in exact)}, not whole pixels",
                         fix="crop the sequence first, then resize it (or crop at multiples of the resize ratio)")
    return seq.replace(
        intrinsics=K, height=height, width=width, mask=seq.mask[y0 : y0 + height, x0 : x0 + width], native_window=window
    )


def downsample_and_crop_to_mask(seq: Sequence, factor: int = 4, multiple: int = 64) -> Sequence:
    """The original method's preprocessing: downsample by ``factor``, then crop the mask's bounding box to a
    multiple of ``multiple`` pixels (so that the network's strides divide the image)."""
    # sides cut to multiples of ``factor`` first, so that the crop below falls on whole native pixels
    whole = crop_sequence(seq, 0, 0, seq.width // factor * factor, seq.height // factor * factor)
    small = resize_sequence(whole, whole.height // factor, whole.width // factor)
    x0, y0, w, h = mask_bbox_crop(torch.from_numpy(small.mask), multiple)
    return crop_sequence(small, x0, y0, w, h)

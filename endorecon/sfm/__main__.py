"""``python -m endorecon.sfm input=<frames dir | sequence folder> out=<dir> [options]``

Options (key=value):
    input     a folder of frames, or a sequence folder (frames/, camera.json, mask.png)
    out       output folder (resumable: complete work is skipped)
    fx fy cx cy   intrinsics in pixels at the frames' size, pixel-centre convention
    camera    a camera.json instead of fx/fy/cx/cy
    mask      valid-pixel mask image (white = valid); default: the sequence's mask.png,
              else estimated from the frames (pixels that are ever brighter than black)
    name      sequence name (default: the input folder's name)
    any other key overrides conf/sfm/default.yaml, e.g. max_size=640 allow_partial=true clean.visibility_window=3
              (a leading "sfm." is accepted: sfm.allow_partial=true, as train.py / reconstruct.py spell it)
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np

from endorecon.utils.errors import EndoreconError, InputError

CONF = Path(__file__).resolve().parents[2] / "conf" / "sfm" / "default.yaml"
OWN_KEYS = {"input", "out", "fx", "fy", "cx", "cy", "camera", "mask", "name"}


def parse_args(argv: list[str]) -> tuple[dict, list[str]]:
    own, overrides = {}, []
    for a in argv:
        if a in ("-h", "--help", "help"):
            print(__doc__.strip())
            raise SystemExit(0)
        if "=" not in a:
            raise InputError(f"argument {a!r} is not key=value", fix=__doc__.strip().splitlines()[0])
        k, v = a.split("=", 1)
        if k in OWN_KEYS:
            own[k] = v
        else:
            overrides.append(a[len("sfm."):] if k.startswith("sfm.") else a)
    for k in ("input", "out"):
        if k not in own:
            raise InputError(f"missing {k}=", fix=__doc__.strip().splitlines()[0])
    return own, overrides


def estimate_mask(frames: list[Path], max_frames: int = 10) -> np.ndarray:
    """Valid pixels = ever brighter than near-black in a few frames (the endoscope's dark border is never lit)."""
    from scipy import ndimage

    from endorecon.data.sequence import read_rgb

    pick = np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int)
    bright = None
    for i in pick:
        g = read_rgb(frames[i]).max(axis=2) > 12
        bright = g if bright is None else bright | g
    mask = ndimage.binary_opening(bright, iterations=2)
    mask = ndimage.binary_fill_holes(mask)
    if mask.mean() < 0.05:
        raise InputError("could not estimate a mask: the frames are almost black", frames[0].parent,
                         "pass mask=<png> (white = valid)")
    return mask


def build_sequence(own: dict):
    from endorecon.data.sequence import (
        Sequence,
        list_frames,
        load_sequence_folder,
        read_camera_json,
        read_mask,
        read_rgb,
    )

    src = Path(own["input"])
    if (src / "camera.json").is_file() and (src / "frames").is_dir():
        seq = load_sequence_folder(src, name=own.get("name"))
        if "mask" in own:
            seq = seq.replace(mask=read_mask(own["mask"], expect_hw=(seq.height, seq.width)))
        return seq
    frames = list_frames(src)
    h, w = read_rgb(frames[0]).shape[:2]
    if "camera" in own:
        K, ch, cw, _ = read_camera_json(own["camera"])
        if (ch, cw) != (h, w):
            raise InputError(f"camera.json is for {cw}x{ch} but frames are {w}x{h}", own["camera"],
                             "give intrinsics at the frames' size")
    elif all(k in own for k in ("fx", "fy", "cx", "cy")):
        try:
            fx, fy, cx, cy = (float(own[k]) for k in ("fx", "fy", "cx", "cy"))
        except ValueError as e:
            raise InputError(f"intrinsics must be numbers ({e})") from e
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    else:
        raise InputError("the intrinsics are needed (SfM runs with known intrinsics)", src,
                         "pass fx= fy= cx= cy= (pixels, pixel-centre convention) or camera=<camera.json>")
    mask = read_mask(own["mask"], expect_hw=(h, w)) if "mask" in own else estimate_mask(frames)
    return Sequence(name=own.get("name", src.name), frame_paths=frames, intrinsics=K, height=h, width=w,
                    mask=mask, source="video")


def main(argv: list[str] | None = None) -> int:
    from omegaconf import OmegaConf
    from rich.console import Console
    from rich.logging import RichHandler

    console = Console(stderr=True)
    logging.basicConfig(level=logging.INFO, format="%(message)s", handlers=[RichHandler(console=console)])
    try:
        own, overrides = parse_args(sys.argv[1:] if argv is None else argv)
        if not CONF.is_file():
            raise InputError("SfM config not found", CONF, "run from a checkout of endorecon")
        base = OmegaConf.load(CONF)
        OmegaConf.set_struct(base, True)  # a misspelt key is refused, not ignored
        try:
            cfg = OmegaConf.merge(base, OmegaConf.from_dotlist(overrides))
        except Exception as e:  # omegaconf's ConfigKeyError / ValidationError
            known = ", ".join(sorted(OWN_KEYS | set(base.keys())))
            raise InputError(f"unknown or invalid SfM option ({str(e).splitlines()[0]})", CONF,
                             f"use one of: {known} (or clean.<key>)") from e
        from endorecon.sfm.stage import load_result, run

        seq = build_sequence(own)
        out = run(cfg, seq, own["out"])
        res = load_result(out)
        console.print(
            f"[green]SfM done[/green]: {int(res.registered.sum())}/{len(res)} frames registered, "
            f"{len(res.points_xyz)} points -> {out}/sequence.npz, {out}/model"
        )
        return 0
    except EndoreconError as e:
        from endorecon.utils.cli import print_error

        print_error(e)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""Contact sheet of a phantom sequence (frames, GT depth, mask) and a side-by-side with a real frame.

``python -m endorecon.phantom.contact_sheet <dataset> <out.png> [--real <frame.jpg> --side <out2.png> --extra <frame.jpg> ...]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from endorecon.utils.io import atomic_path


def _colourise(depth: np.ndarray, vmax: float) -> np.ndarray:
    import matplotlib

    rgb = matplotlib.colormaps["turbo"](np.clip(depth / vmax, 0, 1))[..., :3]
    rgb[depth <= 0] = 0
    return (rgb * 255).astype(np.uint8)


def contact_sheet(root: str | Path, out: str | Path, patients=(0, 1, 2), frames_per_row: int = 4, seq: str = "seq_00") -> Path:
    """Rows per patient: ``frames_per_row`` frames then their GT depth; last tile the mask. Writes a PNG."""
    from PIL import Image

    from endorecon.data.dataset import load_dataset, load_ground_truth

    seqs = {s.patient: s for s in load_dataset(root) if s.name.endswith(seq)}
    rows = []
    for p in patients:
        if p not in seqs:
            continue
        s = seqs[p]
        gt = load_ground_truth(root, p, seq)
        idx = np.linspace(0, len(s) - 1, frames_per_row).round().astype(int)
        vmax = float(np.percentile(gt.depth_mm[gt.depth_mm > 0], 95))
        tiles = [s.load_frame(i) for i in idx] + [_colourise(gt.depth_mm[i], vmax) for i in idx[:2]]
        tiles.append(np.repeat((s.mask * 255).astype(np.uint8)[..., None], 3, 2))
        rows.append(np.concatenate([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=255) for t in tiles], 1))
    sheet = np.concatenate(rows, 0)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # an adaptive 256-colour palette keeps the README image small (~1/3 of the RGB PNG)
    with atomic_path(out) as tmp:
        Image.fromarray(sheet).quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
            tmp, optimize=True)
    return out


def side_by_side(phantom_frames, real_frame: str | Path, out: str | Path, real_mask: str | Path | None = None) -> Path:
    """Phantom frame(s) next to a real one (cropped to its mask's bounding box, resized to the same height)."""
    from PIL import Image

    if isinstance(phantom_frames, (str, Path)):
        phantom_frames = [phantom_frames]
    tiles = [np.asarray(Image.open(f).convert("RGB")) for f in phantom_frames]
    h = tiles[0].shape[0]
    real = Image.open(real_frame).convert("RGB")
    if real_mask is not None:
        m = np.asarray(Image.open(real_mask).convert("L")) > 127
        ys, xs = np.nonzero(m)
        real = real.crop((xs.min(), ys.min(), xs.max() + 1, ys.max() + 1))
    tiles.append(np.asarray(real.resize((round(real.width * h / real.height), h), Image.BICUBIC)))
    gap = np.full((h, 8, 3), 255, np.uint8)
    row = [tiles[0]]
    for t in tiles[1:]:
        row += [gap, t]
    out = Path(out)
    with atomic_path(out) as tmp:
        Image.fromarray(np.concatenate(row, 1)).save(tmp)
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("root")
    ap.add_argument("out")
    ap.add_argument("--real", default=None, help="a real frame for the side-by-side")
    ap.add_argument("--real-mask", default=None)
    ap.add_argument("--side", default=None, help="output PNG of the side-by-side")
    ap.add_argument("--frame", type=int, default=10)
    ap.add_argument("--extra", nargs="*", default=[], help="more phantom frames for the side-by-side")
    a = ap.parse_args()
    print(contact_sheet(a.root, a.out))
    if a.real and a.side:
        first = Path(a.root) / "patient_00/seq_00/frames" / f"{a.frame:06d}.jpg"
        print(side_by_side([first, *a.extra], a.real, a.side, a.real_mask))

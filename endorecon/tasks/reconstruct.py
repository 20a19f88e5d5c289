"""The reconstruct task: a new video -> SfM -> depth + std -> failures -> PGO -> fusion -> mesh + report.

``python reconstruct.py input=<video | frames folder | sequence folder | original-format folder>
[intrinsics=<camera.json | fx fy cx cy file>] [mask=<png>] [ckpt=<checkpoint>]``

Every stage writes into the run dir and is skipped when its outputs exist, so
an interrupted run resumes and a failed stage loses nothing already written.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from endorecon.data.sequence import Sequence, list_frames, load_sequence_folder, read_mask, read_rgb
from endorecon.data.transforms import resize_sequence
from endorecon.tasks import pipeline
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_save_npz, atomic_write_text

log = logging.getLogger(__name__)


def _input_sequence(cfg: DictConfig, out: Path) -> Sequence:
    """The input as a Sequence without poses (frames, K, mask)."""
    from endorecon.data.video import VIDEO_SUFFIXES, estimate_mask, extract_frames, read_intrinsics

    if cfg.input is None:
        raise InputError("no input given", fix="pass input=<video file or frames folder>")
    src = Path(str(cfg.input))
    if not src.exists():
        raise InputError("input does not exist", src, "pass input=<video file or frames folder>")
    if src.is_dir() and (src / "camera.json").is_file() and (src / "frames").is_dir():
        seq = load_sequence_folder(src)
        return seq.replace(cam_from_world=np.full((len(seq), 4, 4), np.nan), points_xyz=None, visibility=None)
    if src.is_dir() and (src / "camera_intrinsics_per_view").is_file() and cfg.intrinsics is None:
        from endorecon.data.original import load_original

        seq = load_original(src)
        return Sequence(name=src.name, frame_paths=seq.frame_paths, intrinsics=seq.intrinsics, height=seq.height,
                        width=seq.width, mask=seq.mask, source="original")
    if src.is_file() and src.suffix.lower() in VIDEO_SUFFIXES:
        frames = extract_frames(src, out / "frames", stride=int(cfg.video.stride), max_frames=cfg.video.max_frames)
        source = "video"
    elif src.is_dir():
        frames = list_frames(src)
        source = "frames"
    else:
        raise InputError(f"unsupported input type {src.suffix!r}", src,
                         f"pass a video ({', '.join(VIDEO_SUFFIXES)}) or a folder of frames")
    first = read_rgb(frames[0])
    h, w = first.shape[:2]
    if cfg.intrinsics is None:
        raise InputError("no intrinsics given: self-calibration fails on endoscopy", src,
                         "pass intrinsics=<camera.json or a file with 'fx fy cx cy'>")
    K = read_intrinsics(cfg.intrinsics, pixel_origin=str(cfg.intrinsics_pixel_origin))
    if cfg.mask is not None:
        mask = read_mask(cfg.mask, expect_hw=(h, w))
    else:
        sample = [read_rgb(p, expect_hw=(h, w)) for p in frames[:: max(1, len(frames) // 10)]]
        mask = estimate_mask(sample)
    return Sequence(name=src.stem, frame_paths=frames, intrinsics=K, height=h, width=w, mask=mask, source=source)


def load_module(ckpt: str | Path):
    from endorecon.module import DepthModule

    ckpt = Path(str(ckpt))
    if not ckpt.is_file():
        raise InputError("checkpoint does not exist", ckpt, "train first (python train.py) or pass ckpt=<path>")
    try:
        module = DepthModule.load_from_checkpoint(str(ckpt), map_location="cpu")
    except (RuntimeError, KeyError, TypeError, ValueError, EOFError) as e:
        raise InputError(f"cannot load this checkpoint as a depth model ({type(e).__name__}: {str(e)[:300]})", ckpt,
                         "pass a checkpoint written by train.py (checkpoints/last.ckpt)") from e
    return module.eval()


def _latest_checkpoint(cfg) -> Path:
    cands = sorted(Path(cfg.paths.output_root).glob("train/fold=*/iteration=*/checkpoints/last.ckpt"),
                   key=lambda p: p.stat().st_mtime)
    if not cands:
        raise InputError("no checkpoint given and none found under outputs/train",
                         fix="train first (python train.py) or pass ckpt=<path>")
    return cands[-1]


def run(cfg: DictConfig) -> Path:
    out = Path(cfg.paths.run_dir)
    out.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}

    t0 = time.perf_counter()
    seq = _input_sequence(cfg, out)
    times["frames"] = time.perf_counter() - t0
    log.info("%s: %d frames %dx%d", seq.name, len(seq), seq.width, seq.height)

    t0 = time.perf_counter()
    from endorecon.sfm.stage import load_result
    from endorecon.sfm.stage import run as sfm_run

    sfm_run(cfg.sfm, seq, out / "sfm")
    sfm_seq = load_result(out / "sfm")
    times["sfm"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ckpt = cfg.ckpt if cfg.ckpt is not None else _latest_checkpoint(cfg)
    module = load_module(ckpt)
    hw = module.hparams.get("input_hw") if hasattr(module, "hparams") else None
    height, width = (int(hw[0]), int(hw[1])) if hw else (int(cfg.data.height), int(cfg.data.width))
    small = resize_sequence(sfm_seq, height, width)
    from endorecon.data.sparse import build_sparse_cache

    cache = build_sparse_cache(small)
    depth_file = out / "depth.npz"
    if depth_file.is_file():
        z = np.load(depth_file)
        depth, std, colors = torch.from_numpy(z["depth"]), torch.from_numpy(z["std"]), z["colors"]
    else:
        depth, std, colors = pipeline.infer_depth(module, small, cache)
        atomic_save_npz(depth_file, depth=depth.numpy(), std=std.numpy(), colors=colors)
    times["inference"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    summary = pipeline.refine_sequence(cfg, small, cache, depth, std, colors, None, out / "reconstruction")
    times["failure_pgo_fusion"] = time.perf_counter() - t0
    for k, v in summary.get("times", {}).items():
        times[f"  {k}"] = v

    report = write_report(out, small, summary, depth, std, colors, times, ckpt)
    log.info("mesh: %s\nreport: %s", out / "reconstruction" / "mesh.ply", report)
    return out


def write_report(out: Path, seq: Sequence, summary: dict, depth, std, colors, times: dict, ckpt) -> Path:
    """``report.md`` with per-stage timings, flagged frames, and PNGs (depth/std samples, mesh preview)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(seq)
    picks = sorted(set(np.linspace(0, n - 1, min(4, n)).astype(int).tolist()))
    fig, axes = plt.subplots(3, len(picks), figsize=(3 * len(picks), 7.5), squeeze=False)
    for c, i in enumerate(picks):
        m = seq.mask
        d = np.where(m, depth[i, 0].numpy(), np.nan)
        s = np.where(m, std[i, 0].numpy(), np.nan)
        axes[0, c].imshow(colors[i])
        axes[0, c].set_title(f"frame {i}")
        im = axes[1, c].imshow(d, cmap="turbo")
        plt.colorbar(im, ax=axes[1, c], fraction=0.046)
        im = axes[2, c].imshow(s, cmap="magma")
        plt.colorbar(im, ax=axes[2, c], fraction=0.046)
        for r in range(3):
            axes[r, c].axis("off")
    axes[1, 0].set_title("depth (SfM units)", loc="left")
    axes[2, 0].set_title("std", loc="left")
    fig.tight_layout()
    fig.savefig(out / "depth_std.png", dpi=80)
    plt.close(fig)
    preview = out / "mesh_preview.png"
    try:
        from endorecon.evaluation.plots import render_mesh_preview

        render_mesh_preview(out / "reconstruction" / "mesh.ply", preview)
    except Exception as e:  # a missing preview must not hide the mesh itself
        log.warning("mesh preview failed: %s", e)
    total = sum(v for k, v in times.items() if not k.startswith(" "))
    lines = [
        f"# Reconstruction of {seq.name}",
        "",
        f"- frames: {n} ({seq.width}x{seq.height} at the network's resolution), registered by SfM: "
        f"{summary['registered']}, fused: {summary['fused']}",
        f"- flagged by failure detection: {summary['n_flagged']} {summary['flagged']}",
        f"- checkpoint: `{ckpt}`",
        f"- mesh: `reconstruction/mesh.ply` (coloured, per-vertex std)",
        "",
        "| stage | time (s) |",
        "| --- | ---: |",
        *[f"| {k} | {v:.1f} |" for k, v in times.items()],
        f"| **total** | **{total:.1f}** |",
        "",
        "![depth and std](depth_std.png)",
        "",
        "![mesh preview](mesh_preview.png)",
        "",
    ]
    atomic_write_text(out / "report.md", "\n".join(lines))
    atomic_write_text(out / "timings.json", json.dumps(times, indent=2) + "\n")
    return out / "report.md"

"""Fusion stage: build a TSDF volume from config and fuse a stream of frames into ``mesh.ply``."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Mapping
from itertools import chain
from pathlib import Path

from endorecon.fusion.tsdf import AdaptiveTSDF, PlainTSDF, median_valid_depth
from endorecon.utils.errors import InputError

__all__ = ["FUSION_DEFAULTS", "build_fusion", "fuse_frames", "median_valid_depth"]

log = logging.getLogger(__name__)


def _get(cfg, key, default=None):
    if isinstance(cfg, Mapping):
        return cfg.get(key, default)
    return getattr(cfg, key, default) if hasattr(cfg, key) else default


# What a ``fusion`` config without a key gets (older run configs lack the keys added since)
FUSION_DEFAULTS = dict(
    name="adaptive", voxel_size=None, voxel_fraction=0.01, depth_max_factor=None, block_resolution=8,
    block_count=20000, mesh_weight_threshold=1.0, device="auto", min_component_fraction=0.0,
    boundary_trim_rings=0, mask_erode_px=0, c1=0.1, c2=0.8, trunc_std_multiplier=3.0, trunc_min_voxels=6.0,
    trunc_max_voxels=24.0, std_mode="propagate", compile=False, trunc_voxels=6.0, block_search="sampled",
    free_space_max_fraction=None, free_space_tau=0.1, max_std_ratio=None, max_nearest_view_ratio=None,
)


def build_fusion(cfg_fusion, median_depth: float | None = None) -> AdaptiveTSDF | PlainTSDF:
    """Volume from the ``fusion`` config group (``conf/fusion/{adaptive,plain}.yaml``).

    Args:
        cfg_fusion: mapping / DictConfig with ``name`` (adaptive | plain) and the keys of those files.
        median_depth: median valid depth of the sequence, in its units; sets the
            voxel (``voxel_fraction`` x it) when ``voxel_size`` is null and the
            depth cut-off (``depth_max_factor`` x it).
    """
    def get(key):
        return _get(cfg_fusion, key, FUSION_DEFAULTS[key])

    name = get("name")
    voxel = get("voxel_size")
    med = None if median_depth is None else float(median_depth)
    if voxel is None:
        if med is None or not (math.isfinite(med) and med > 0):
            raise InputError(f"fusion.voxel_size is null and the median depth ({median_depth}) is not a positive number",
                             fix="set fusion.voxel_size, or fuse frames with valid depth")
        voxel = float(get("voxel_fraction")) * med
    factor = get("depth_max_factor")
    depth_max = float("inf")
    if factor is not None:
        if med is None or not (math.isfinite(med) and med > 0):  # the cut-off was dropped without a word
            raise InputError(f"fusion.depth_max_factor is set and the median depth ({median_depth}) is not a "
                             f"positive number", fix="fuse frames with valid depth, or set fusion.depth_max_factor=null")
        depth_max = float(factor) * med
    common = dict(
        voxel_size=float(voxel),
        depth_max=depth_max,
        block_resolution=int(get("block_resolution")),
        block_count=int(get("block_count")),
        mesh_weight_threshold=float(get("mesh_weight_threshold")),
        device=str(get("device")),
        min_component_fraction=float(get("min_component_fraction")),
        boundary_trim_rings=int(get("boundary_trim_rings")),
        mask_erode_px=get("mask_erode_px"),
        block_search=str(get("block_search")),
        free_space_max_fraction=get("free_space_max_fraction"),
        free_space_tau=get("free_space_tau"),
        max_nearest_view_ratio=get("max_nearest_view_ratio"),
    )
    if name == "adaptive":
        return AdaptiveTSDF(
            c1=float(get("c1")),
            c2=float(get("c2")),
            trunc_std_multiplier=float(get("trunc_std_multiplier")),
            trunc_min_voxels=float(get("trunc_min_voxels")),
            trunc_max_voxels=float(get("trunc_max_voxels")),
            std_mode=str(get("std_mode")),
            compile=bool(get("compile")),
            max_std_ratio=get("max_std_ratio"),
            **common,
        )
    if name == "plain":
        return PlainTSDF(trunc_voxels=float(get("trunc_voxels")), **common)
    raise InputError(f"unknown fusion.name {name!r}", fix="use fusion=adaptive or fusion=plain")


def _check_frame_keys(frame: dict, n: int, cfg_fusion) -> None:
    adaptive = _get(cfg_fusion, "name", FUSION_DEFAULTS["name"]) == "adaptive"
    keys = ("depth", "color", "K", "cam_from_world") + (("std",) if adaptive else ())
    for key in keys:
        if key not in frame:
            raise InputError(f"fusion: frame {n} has no {key!r}",
                             fix="yield dicts with depth, std, color, K, cam_from_world, mask")


def fuse_frames(cfg_fusion, frames_iter: Iterable[Mapping], out_path: str | Path,
                median_depth: float | None = None, total: int | None = None) -> Path:
    """Fuse every frame of ``frames_iter`` and write the mesh to ``out_path`` (PLY, atomic).

    Skips all work when ``out_path`` exists.

    Args:
        cfg_fusion: the ``fusion`` config group.
        frames_iter: yields dicts ``{depth (H,W), std (H,W), color (H,W,3) in [0,1],
            K (3,3) pixel-centre, cam_from_world (4,4), mask (H,W) bool | None}``.
        out_path: mesh file to write (``mesh.ply``).
        median_depth: the sequence's median valid depth; None -> that of the first frame with valid depth.
        total: number of frames, for the progress bar (default: ``len(frames_iter)`` if defined).
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    out_path = Path(out_path)
    if out_path.exists():
        log.info("fusion: %s exists, skipping", out_path)
        return out_path
    if total is None and hasattr(frames_iter, "__len__"):
        total = len(frames_iter)  # type: ignore[arg-type]
    it = iter(frames_iter)
    head = []  # frames read ahead until one has valid depth (its median sets the voxel and the cut-off)
    for fr in it:
        _check_frame_keys(fr, len(head), cfg_fusion)
        head.append(fr)
        if median_depth is not None:
            break
        med = median_valid_depth(fr["depth"], fr.get("mask"))
        if math.isfinite(med) and med > 0:
            median_depth = med
            break
    if not head:
        raise InputError("fusion: no frames to fuse", out_path, fix="check the failure flags / registered frames")
    if median_depth is None:
        raise InputError(f"fusion: none of the {len(head)} frames has a finite, positive depth inside its mask",
                         out_path, "check the depth maps (NaN, zeros) and the mask")
    volume = build_fusion(cfg_fusion, median_depth)
    t0 = time.perf_counter()
    n = 0
    with Progress(TextColumn("fusion"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), transient=True) as bar:
        task = bar.add_task("fuse", total=total)
        for fr in chain(head, it):
            _check_frame_keys(fr, n, cfg_fusion)
            volume.integrate(fr["depth"], fr.get("std"), fr["color"], fr["K"], fr["cam_from_world"], fr.get("mask"))
            n += 1
            bar.advance(task)
    dt = time.perf_counter() - t0
    volume.save_mesh(out_path)
    log.info("fusion: %d frames in %.1f s (%.1f frames/s), voxel %.4g -> %s", n, dt, n / max(dt, 1e-9), volume.voxel_size, out_path)
    return out_path

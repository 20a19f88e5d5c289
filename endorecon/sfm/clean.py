"""Cleaning the sparse SfM cloud for training, and the global scale normalisation.

The depth network is supervised by the sparse points (sparse depth, sparse flow),
so a wrong point is a wrong label.  :func:`clean_sparse` applies, in this order:

1. **Track length / reprojection error.**  Drop points seen in fewer than
   ``min_track_length`` frames, or whose mean reprojection error (COLMAP's,
   in SfM-resolution pixels) exceeds ``max_reproj_error``.
2. **Visibility smoothing.**  SIFT misses a point in some frames it is plainly
   in view.  If a point is seen at frames i and i+k with 1 < k <= ``visibility_window``,
   it is treated as visible at every frame in between where it projects in
   front of the camera and inside the (valid-pixel) mask.
3. **Far and dark observations.**  The original method discarded far, dark
   points (light falls off with depth; deep, dark regions give unreliable
   SIFT matches).  Equivalent here, per observation (frame f, point p):
   drop it if its z-depth in f exceeds ``max_depth_ratio`` x the median
   z-depth of the sparse points seen in f, or if the grey value of frame f at
   the point's projection (in [0, 1]) is below ``min_brightness``.  Also drop
   observations behind the camera or outside the mask.
4. Drop points left with fewer than ``min_observations`` observations.

**Scale normalisation** (:func:`normalize_scale`): the SfM scale is arbitrary;
the world is scaled so that the median sparse z-depth over all (frame, point)
observations is 1.  The factor is returned (and logged by the stage); units stay
``"sfm"``.  Per-frame scale is absorbed later by the depth scaling layer.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from endorecon.geometry import project, transform_points


def project_all(cam_from_world: np.ndarray, K: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project every point into every frame.

    Args:
        cam_from_world: (N, 4, 4) (NaN rows allowed: they give NaN).
        K: (3, 3) pixel-centre intrinsics.
        points: (P, 3) world points.
    Returns:
        uv (N, P, 2), z (N, P).
    """
    N, P = len(cam_from_world), len(points)
    T = torch.from_numpy(np.nan_to_num(cam_from_world, nan=0.0))
    pts = torch.from_numpy(points).expand(N, P, 3)
    uv, z = project(transform_points(T, pts), torch.from_numpy(K).expand(N, 3, 3).contiguous())
    uv, z = uv.numpy(), z.numpy()
    bad = ~np.isfinite(cam_from_world).all(axis=(1, 2))
    uv[bad] = np.nan
    z[bad] = np.nan
    return uv, z


def inside_mask(uv: np.ndarray, z: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(…) bool: in front of the camera and projecting onto a valid mask pixel (nearest pixel)."""
    H, W = mask.shape
    with np.errstate(invalid="ignore"):
        col = np.rint(uv[..., 0])
        row = np.rint(uv[..., 1])
        ok = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    out = np.zeros(z.shape, dtype=bool)
    out[ok] = mask[row[ok].astype(int), col[ok].astype(int)]
    return out


def smooth_visibility(visible: np.ndarray, candidate: np.ndarray, window: int) -> np.ndarray:
    """Fill short gaps in visibility.

    Args:
        visible: (N, P) bool, point p observed in frame f.
        candidate: (N, P) bool, p could be visible in f (in front, inside the mask).
        window: a gap between observations at f and f+k is filled when k <= window.
    Returns:
        (N, P) bool: visible, plus candidate frames strictly inside short gaps.
    """
    N, P = visible.shape
    f = np.arange(N)[:, None]
    prev = np.where(visible, f, -(10**9))
    prev = np.maximum.accumulate(prev, axis=0)
    nxt = np.where(visible, f, 10**9)
    nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
    gap = (nxt - prev) <= window
    return visible | (gap & candidate)


def _sample_nearest(gray: np.ndarray, uv: np.ndarray) -> np.ndarray:
    H, W = gray.shape
    col = np.clip(np.rint(uv[:, 0]), 0, W - 1).astype(int)
    row = np.clip(np.rint(uv[:, 1]), 0, H - 1).astype(int)
    return gray[row, col]


def clean_sparse(
    cam_from_world: np.ndarray,
    K: np.ndarray,
    mask: np.ndarray,
    points_xyz: np.ndarray,
    visibility: list[np.ndarray],
    errors: np.ndarray | None = None,
    load_gray: Callable[[int], np.ndarray] | None = None,
    min_track_length: int = 3,
    max_reproj_error: float = 2.0,
    visibility_window: int = 5,
    max_depth_ratio: float = 3.0,
    min_brightness: float = 0.05,
    min_observations: int = 2,
    chunk: int = 4096,
) -> tuple[np.ndarray, list[np.ndarray], dict]:
    """Clean sparse points (see the module docstring for the rules).

    Args:
        cam_from_world: (N, 4, 4), NaN rows for unregistered frames.
        K: (3, 3) pixel-centre intrinsics at the mask's size.
        mask: (H, W) bool.
        points_xyz: (P, 3); visibility: P int arrays of frame indices.
        errors: (P,) mean reprojection errors in pixels at (H, W), or None (no error filter).
        load_gray: frame index -> (H, W) grey image in [0, 1], or None (no brightness filter).
    Returns:
        (kept points (Q, 3), their visibility (Q arrays), stats dict with the counts removed at each step
        and ``kept_index`` (Q,) into the input points).
    """
    P = len(points_xyz)
    N = len(cam_from_world)
    stats: dict = dict(input_points=P)
    track = np.array([len(v) for v in visibility], dtype=np.int64)
    keep = track >= min_track_length
    stats["short_tracks"] = int((~keep).sum())
    if errors is not None and len(errors) == P:
        bad_err = keep & ~(np.nan_to_num(errors, nan=np.inf) <= max_reproj_error)
        stats["high_reproj_error"] = int(bad_err.sum())
        keep &= ~bad_err
    idx = np.nonzero(keep)[0]
    registered = np.isfinite(cam_from_world).all(axis=(1, 2))

    vis_rows, vis_cols, depth_all, uv_rows = [], [], [], []
    added = 0
    for c0 in range(0, len(idx), chunk):
        sel = idx[c0 : c0 + chunk]
        uv, z = project_all(cam_from_world, K, points_xyz[sel])
        visible = np.zeros((N, len(sel)), dtype=bool)
        for j, p in enumerate(sel):
            v = visibility[p]
            visible[v[(v >= 0) & (v < N)], j] = True
        visible &= registered[:, None]
        cand = inside_mask(uv, z, mask)
        smooth = smooth_visibility(visible, cand, visibility_window) if visibility_window > 1 else visible
        added += int((smooth & ~visible).sum())
        smooth &= cand  # behind the camera / outside the mask: not an observation we can use
        f, j = np.nonzero(smooth)
        vis_rows.append(f)
        vis_cols.append(sel[j])
        depth_all.append(z[f, j])
        uv_rows.append(uv[f, j])
    stats["smoothing_added"] = added
    f_all = np.concatenate(vis_rows) if vis_rows else np.zeros(0, np.int64)
    p_all = np.concatenate(vis_cols) if vis_cols else np.zeros(0, np.int64)
    z_all = np.concatenate(depth_all) if depth_all else np.zeros(0)
    uv_all = np.concatenate(uv_rows) if uv_rows else np.zeros((0, 2))

    ok = np.ones(len(f_all), dtype=bool)
    # far: z above max_depth_ratio x the frame's median sparse depth
    for fr in np.unique(f_all):
        m = f_all == fr
        med = np.median(z_all[m])
        ok[m] &= z_all[m] <= max_depth_ratio * med
    stats["far_observations"] = int((~ok).sum())
    if load_gray is not None and min_brightness > 0:
        dark = 0
        for fr in np.unique(f_all):
            m = np.nonzero((f_all == fr) & ok)[0]
            if len(m) == 0:
                continue
            g = _sample_nearest(load_gray(int(fr)), uv_all[m])
            d = g < min_brightness
            ok[m[d]] = False
            dark += int(d.sum())
        stats["dark_observations"] = dark
    f_all, p_all = f_all[ok], p_all[ok]

    order = np.lexsort((f_all, p_all))
    f_all, p_all = f_all[order], p_all[order]
    uniq, start, counts = np.unique(p_all, return_index=True, return_counts=True)
    good = counts >= min_observations
    kept_index = uniq[good]
    new_vis = [f_all[s : s + c].astype(np.int64) for s, c, g in zip(start, counts, good) if g]
    stats["few_observations"] = int(len(idx) - good.sum())
    stats["kept_points"] = int(len(kept_index))
    stats["kept_index"] = kept_index
    return points_xyz[kept_index], new_vis, stats


def sparse_depths(cam_from_world: np.ndarray, points_xyz: np.ndarray, visibility: list[np.ndarray]) -> np.ndarray:
    """z-depths of all (frame, point) observations, (M,)."""
    if not visibility:
        return np.zeros(0)
    f = np.concatenate(visibility)
    p = np.repeat(np.arange(len(visibility)), [len(v) for v in visibility])
    R = cam_from_world[f, :3, :3]
    t = cam_from_world[f, :3, 3]
    return np.einsum("mj,mj->m", R[:, 2], points_xyz[p]) + t[:, 2]


def normalize_scale(
    cam_from_world: np.ndarray, points_xyz: np.ndarray, visibility: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, float]:
    """Scale the world so that the median sparse z-depth over all observations is 1.

    Returns:
        (cam_from_world with scaled translations, scaled points, factor s; new = s x old).
    """
    z = sparse_depths(cam_from_world, points_xyz, visibility)
    z = z[np.isfinite(z) & (z > 0)]
    if len(z) == 0:
        return cam_from_world, points_xyz, 1.0
    s = 1.0 / float(np.median(z))
    T = cam_from_world.copy()
    T[:, :3, 3] *= s
    return T, points_xyz * s, s

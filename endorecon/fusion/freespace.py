"""View checks of a fused mesh: drop surface that the frames see through, or see only from far.

A TSDF fuses each frame's depth only inside its truncation band, so a frame
whose depth lies far behind a fused surface leaves that surface untouched: a
piece fused by a few frames (a depth outlier, a far region predicted too
near) survives although many other frames look straight through it.  Here a
mesh vertex is judged by every fused frame that has it in view:

* *on surface*: the frame's depth at the vertex's pixel is within ``tau`` (relative) of the vertex's
  z-depth, ``|d - z| <= tau z``;
* *seen through*: the frame's depth there is farther, ``d > (1 + tau) z``: the frame sees free space
  where the vertex is;
* neither (``d < (1 - tau) z``): something nearer hides the vertex from that frame, which says nothing.

A vertex seen through by more than ``max_fraction`` of the frames that are on it or see through it
is free space, not surface.

The nearest view of a vertex is the smallest z-depth at which a fused frame has it on its surface.  A
vertex whose nearest view is farther than ``max_ratio`` x the fused frames' median depth was seen only
from far: a monocular network's far depth is its least accurate (compressed towards the camera, and by
about the same amount in every frame that sees it from that far, so no multi-view check notices), and
there is no nearer frame to correct it (:func:`drop_far_only`).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import open3d.core as o3c
import torch

from endorecon.geometry import project, transform_points
from endorecon.utils.errors import InputError, optional_number_above

__all__ = ["free_space_counts", "surface_views", "seen_through_fraction", "drop_seen_through", "check_free_space_params",
           "check_nearest_view_ratio", "drop_far_only"]


def check_free_space_params(max_fraction, tau) -> tuple[float | None, float]:
    """``(max_fraction or None, tau)`` checked: max_fraction in [0, 1) or None (off), tau in (0, 1)."""
    if max_fraction is not None:
        try:
            ok = not isinstance(max_fraction, bool) and 0.0 <= float(max_fraction) < 1.0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise InputError(f"fusion: free_space_max_fraction must be in [0, 1) or null, got {max_fraction!r}",
                             fix="set fusion.free_space_max_fraction=0.5 (null: no free-space check)")
        max_fraction = float(max_fraction)
    try:
        tau_ok = not isinstance(tau, bool) and 0.0 < float(tau) < 1.0
    except (TypeError, ValueError):
        tau_ok = False
    if not tau_ok:
        raise InputError(f"fusion: free_space_tau must be in (0, 1), got {tau!r}", fix="set fusion.free_space_tau=0.1")
    return max_fraction, float(tau)


def free_space_counts(points: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, cam_from_world: torch.Tensor,
                      mask: torch.Tensor | None = None, tau: float = 0.1) -> tuple[torch.Tensor, torch.Tensor]:
    """How many frames have each point on their surface, and how many see through it (:func:`surface_views`
    without the nearest view)."""
    on, through, _ = surface_views(points, depth, K, cam_from_world, mask, tau)
    return on, through


def surface_views(points: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, cam_from_world: torch.Tensor,
                  mask: torch.Tensor | None = None, tau: float = 0.1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """How many frames have each point on their surface, how many see through it, and the nearest of the first.

    Args:
        points: (P, 3) world points.
        depth: (N, H, W) z-depth of the frames; non-finite or <= 0 pixels say nothing.
        K: (3, 3) or (N, 3, 3) pixel-centre intrinsics.
        cam_from_world: (N, 4, 4).
        mask: (H, W) or (N, H, W) bool, False = pixel says nothing; None = all pixels.
        tau: relative tolerance of "on surface", in (0, 1).
    Returns:
        on: (P,) int64, frames with ``|d - z| <= tau z`` at the point's nearest pixel;
        through: (P,) int64, frames with ``d > (1 + tau) z`` there;
        nearest: (P,) float64, the smallest z of the point in a frame that has it on its surface (inf: none).
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"surface views: points has shape {tuple(points.shape)}, expected (P, 3)")
    if depth.ndim != 3:
        raise InputError(f"surface views: depth has shape {tuple(depth.shape)}, expected (N, H, W)")
    N, H, W = depth.shape
    if cam_from_world.shape != (N, 4, 4):
        raise InputError(f"surface views: cam_from_world has shape {tuple(cam_from_world.shape)}, expected {(N, 4, 4)}")
    K = K.expand(N, 3, 3) if K.shape == (3, 3) else K
    if K.shape != (N, 3, 3):
        raise InputError(f"surface views: K has shape {tuple(K.shape)}, expected (3, 3) or {(N, 3, 3)}")
    if mask is not None:
        mask = mask.expand(N, H, W) if mask.shape == (H, W) else mask
        if mask.shape != (N, H, W):
            raise InputError(f"surface views: mask has shape {tuple(mask.shape)}, expected {(H, W)} or {(N, H, W)}")
    if not 0.0 < float(tau) < 1.0:
        raise InputError(f"surface views: tau must be in (0, 1), got {tau}")
    dev = points.device
    on = torch.zeros(len(points), dtype=torch.int64, device=dev)
    through = torch.zeros_like(on)
    nearest = torch.full((len(points),), float("inf"), dtype=torch.float64, device=dev)
    pts = points.to(torch.float64)
    for i in range(N):  # one frame at a time: memory O(P), not O(N P)
        T = cam_from_world[i : i + 1].to(dev, torch.float64)
        uv, z = project(transform_points(T, pts[None]), K[i : i + 1].to(dev, torch.float64))
        # the project's nearest-pixel rule (endorecon.data.sparse.nearest_pixel): pixel k covers [k - 0.5, k + 0.5)
        u = torch.floor(uv[0, :, 0] + 0.5)
        v = torch.floor(uv[0, :, 1] + 0.5)
        z = z[0]
        inside = (z > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        ui = u.clamp(0, W - 1).long()
        vi = v.clamp(0, H - 1).long()
        d = depth[i].to(dev, torch.float64)[vi, ui]
        ok = inside & torch.isfinite(d) & (d > 0)
        if mask is not None:
            ok &= mask[i].to(dev)[vi, ui].bool()
        on_i = ok & ((d - z).abs() <= tau * z)
        on += on_i
        through += ok & (d > (1.0 + tau) * z)
        nearest = torch.where(on_i, torch.minimum(nearest, z), nearest)
    return on, through, nearest


def seen_through_fraction(on: torch.Tensor, through: torch.Tensor) -> torch.Tensor:
    """``through / (on + through)`` per point; 0 where no frame says anything.  on, through: (P,) -> (P,) float64."""
    n = (on + through).to(torch.float64)
    return torch.where(n > 0, through.to(torch.float64) / n.clamp_min(1.0), torch.zeros_like(n))


def drop_seen_through(mesh: o3d.t.geometry.TriangleMesh, fraction: torch.Tensor | np.ndarray,
                      max_fraction: float) -> o3d.t.geometry.TriangleMesh:
    """Remove the triangles of ``mesh`` with a vertex whose seen-through ``fraction`` (V,) exceeds ``max_fraction``
    (unused vertices go too)."""
    if "indices" not in mesh.triangle or mesh.triangle.indices.shape[0] == 0:
        return mesh
    frac = fraction.cpu().numpy() if isinstance(fraction, torch.Tensor) else np.asarray(fraction)
    n_vertices = int(mesh.vertex.positions.shape[0])
    if frac.shape != (n_vertices,):
        raise InputError(f"free space: fraction has shape {frac.shape}, the mesh has {n_vertices} vertices")
    faces = mesh.triangle.indices.cpu().numpy().astype(np.int64)
    keep = ~(frac[faces] > max_fraction).any(axis=1)
    if keep.all():
        return mesh
    return mesh.select_faces_by_mask(o3c.Tensor(keep, device=mesh.device))


def check_nearest_view_ratio(ratio) -> float | None:
    """``fusion.max_nearest_view_ratio``: None (no check) or a finite number > 0."""
    return optional_number_above(ratio, "fusion: max_nearest_view_ratio", 0.0,
                                 "set fusion.max_nearest_view_ratio=null (keep surface seen only from far) or e.g. 1.4 "
                                 "(drop surface no fused frame sees nearer than 1.4x their median depth)")


def drop_far_only(mesh: o3d.t.geometry.TriangleMesh, nearest: torch.Tensor | np.ndarray, median_depth: float,
                  max_ratio: float | None) -> tuple[o3d.t.geometry.TriangleMesh, dict | None]:
    """Remove the triangles of ``mesh`` with a vertex whose nearest view (``nearest`` (V,), z-depth, inf: none; from
    :func:`surface_views`) is farther than ``max_ratio`` x ``median_depth`` (unused vertices go too).  A vertex that
    no frame has on its surface says nothing and stays.

    Returns the mesh and what was removed (``triangles``, ``removed``, ``median_depth``, ``threshold``, ``ratio``);
    the mesh unchanged and None when ``max_ratio`` is None or the mesh is empty."""
    ratio = check_nearest_view_ratio(max_ratio)
    if ratio is None or "indices" not in mesh.triangle or mesh.triangle.indices.shape[0] == 0:
        return mesh, None
    near = nearest.cpu().numpy() if isinstance(nearest, torch.Tensor) else np.asarray(nearest, dtype=np.float64)
    n_vertices = int(mesh.vertex.positions.shape[0])
    if near.shape != (n_vertices,):
        raise InputError(f"nearest view: nearest has shape {near.shape}, the mesh has {n_vertices} vertices")
    if not (np.isfinite(median_depth) and median_depth > 0):
        raise InputError(f"nearest view: the median depth ({median_depth}) is not a positive number",
                         fix="fuse frames with valid depth, or set fusion.max_nearest_view_ratio=null")
    threshold = ratio * float(median_depth)
    far = np.isfinite(near) & (near > threshold)
    faces = mesh.triangle.indices.cpu().numpy().astype(np.int64)
    keep = ~far[faces].any(axis=1)
    info = dict(triangles=int(len(faces)), removed=int((~keep).sum()), median_depth=float(median_depth),
                threshold=threshold, ratio=ratio)
    if keep.all():
        return mesh, info
    return mesh.select_faces_by_mask(o3c.Tensor(keep, device=mesh.device)), info

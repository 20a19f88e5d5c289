"""Free-space check of a fused mesh: drop surface that the frames see through.

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
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import open3d.core as o3c
import torch

from endorecon.geometry import project, transform_points
from endorecon.utils.errors import InputError

__all__ = ["free_space_counts", "seen_through_fraction", "drop_seen_through", "check_free_space_params"]


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
    """How many frames have each point on their surface, and how many see through it.

    Args:
        points: (P, 3) world points.
        depth: (N, H, W) z-depth of the frames; non-finite or <= 0 pixels say nothing.
        K: (3, 3) or (N, 3, 3) pixel-centre intrinsics.
        cam_from_world: (N, 4, 4).
        mask: (H, W) or (N, H, W) bool, False = pixel says nothing; None = all pixels.
        tau: relative tolerance of "on surface", in (0, 1).
    Returns:
        on: (P,) int64, frames with ``|d - z| <= tau z`` at the point's nearest pixel;
        through: (P,) int64, frames with ``d > (1 + tau) z`` there.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"free space: points has shape {tuple(points.shape)}, expected (P, 3)")
    if depth.ndim != 3:
        raise InputError(f"free space: depth has shape {tuple(depth.shape)}, expected (N, H, W)")
    N, H, W = depth.shape
    if cam_from_world.shape != (N, 4, 4):
        raise InputError(f"free space: cam_from_world has shape {tuple(cam_from_world.shape)}, expected {(N, 4, 4)}")
    K = K.expand(N, 3, 3) if K.shape == (3, 3) else K
    if K.shape != (N, 3, 3):
        raise InputError(f"free space: K has shape {tuple(K.shape)}, expected (3, 3) or {(N, 3, 3)}")
    if mask is not None:
        mask = mask.expand(N, H, W) if mask.shape == (H, W) else mask
        if mask.shape != (N, H, W):
            raise InputError(f"free space: mask has shape {tuple(mask.shape)}, expected {(H, W)} or {(N, H, W)}")
    if not 0.0 < float(tau) < 1.0:
        raise InputError(f"free space: tau must be in (0, 1), got {tau}")
    dev = points.device
    on = torch.zeros(len(points), dtype=torch.int64, device=dev)
    through = torch.zeros_like(on)
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
        on += ok & ((d - z).abs() <= tau * z)
        through += ok & (d > (1.0 + tau) * z)
    return on, through


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

"""Depth fusion: adaptive TSDF (std-driven truncation, exponential averaging) and Open3D's plain TSDF.

* ``kernel``: the per-voxel maths, pure torch.
* ``tsdf``: ``AdaptiveTSDF`` / ``PlainTSDF`` volumes on Open3D's VoxelBlockGrid; the saved mesh's boundary
  trim and (adaptive fusion) uncertainty trim.
* ``freespace``: the view checks of the saved mesh: free space (surface the frames see through) and nearest
  view (surface the frames see only from far).
* ``ply``: mesh PLY with a per-vertex ``std`` property.
* ``run``: ``build_fusion(cfg, median_depth)`` and the ``fuse_frames`` stage.
"""

from endorecon.fusion.freespace import drop_far_only, drop_seen_through, free_space_counts, seen_through_fraction, surface_views
from endorecon.fusion.kernel import averaging_rate, integrate_blocks, truncation
from endorecon.fusion.ply import boundary_trim_rings_of, read_mesh_ply, write_mesh_ply
from endorecon.fusion.run import build_fusion, fuse_frames, median_valid_depth
from endorecon.fusion.tsdf import (AdaptiveTSDF, PlainTSDF, drop_small_components, drop_uncertain, pixel_band_blocks,
                                   trim_boundary)

__all__ = [
    "AdaptiveTSDF",
    "PlainTSDF",
    "build_fusion",
    "fuse_frames",
    "median_valid_depth",
    "averaging_rate",
    "truncation",
    "integrate_blocks",
    "read_mesh_ply",
    "write_mesh_ply",
    "boundary_trim_rings_of",
    "drop_small_components",
    "drop_uncertain",
    "pixel_band_blocks",
    "trim_boundary",
    "free_space_counts",
    "seen_through_fraction",
    "drop_seen_through",
    "surface_views",
    "drop_far_only",
]

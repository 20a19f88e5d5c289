"""TSDF volumes on Open3D's sparse ``VoxelBlockGrid``.

* :class:`AdaptiveTSDF`: the paper's fusion. Open3D provides the hash map of
  8^3 voxel blocks and the block activation; the per-voxel update
  (:func:`endorecon.fusion.kernel.integrate_blocks`) runs in torch on
  zero-copy dlpack views of the grid's buffers, optionally under
  ``torch.compile``, on the grid's device (CPU or CUDA).
* :class:`PlainTSDF`: the baseline, Open3D's own ``integrate`` (fixed
  truncation, running average), fed a corner-convention K because Open3D
  rounds projected pixels down (FACTS.md: otherwise its surface is biased by
  half a pixel).

Both take the same frame arguments (pixel-centre K, ``cam_from_world``, depth
in the sequence's units) and extract a coloured ``open3d.t`` triangle mesh.
"""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
import torch
from torch.utils.dlpack import from_dlpack

from endorecon.fusion.freespace import (check_free_space_params, check_nearest_view_ratio, drop_far_only, drop_seen_through,
                                       seen_through_fraction, surface_views)
from endorecon.fusion.kernel import clean_frame, erode_mask, integrate_blocks, integrate_blocks_, local_voxel_offsets
from endorecon.fusion.ply import write_mesh_ply
from endorecon.geometry import invert_pose, unproject
from endorecon.utils.errors import InputError, optional_number_above
from endorecon.utils.io import atomic_path

__all__ = ["AdaptiveTSDF", "PlainTSDF", "pixel_band_blocks", "resolve_device"]

# How a frame's truncation band is turned into hash-map blocks: "sampled" is Open3D's
# compute_unique_block_coordinates (every 4th pixel, so a block the band crosses between samples can miss
# the frame), "every_pixel" walks the band at every usable pixel (pixel_band_blocks)
BLOCK_SEARCHES = ("sampled", "every_pixel")

log = logging.getLogger(__name__)


def resolve_device(device: str) -> str:
    """Open3D device string: ``"auto"`` -> ``"CUDA:0"`` when Open3D and torch both see CUDA, else ``"CPU:0"``."""
    if device in (None, "auto"):
        if o3c.cuda.is_available() and torch.cuda.is_available():
            return "CUDA:0"
        return "CPU:0"
    dev = o3c.Device(str(device))  # validates the string
    if dev.get_type() == o3c.Device.DeviceType.CUDA and not o3c.cuda.is_available():
        raise InputError(f"fusion device {device!r} requested but this Open3D build sees no CUDA", fix="set fusion.device=auto or CPU:0")
    return str(dev)


def _torch_device(o3d_device: str) -> torch.device:
    dev = o3c.Device(o3d_device)
    if dev.get_type() == o3c.Device.DeviceType.CUDA:
        return torch.device("cuda", dev.get_id())
    return torch.device("cpu")


def _o3c_from_torch(t: torch.Tensor) -> o3c.Tensor:
    return o3c.Tensor.from_dlpack(torch.utils.dlpack.to_dlpack(t.contiguous()))


def _torch_view(t: o3c.Tensor) -> torch.Tensor:
    return from_dlpack(t.to_dlpack())


def _as_array(x, name: str, ndim: int | tuple[int, ...], shape=None) -> torch.Tensor:
    if x is None:
        raise InputError(f"fusion: {name} is None")
    t = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))
    t = t.detach()
    ndims = (ndim,) if isinstance(ndim, int) else ndim
    if t.ndim not in ndims:
        raise InputError(f"fusion: {name} has shape {tuple(t.shape)}, expected {shape or f'{ndim}-D'}")
    return t


def drop_small_components(mesh: o3d.t.geometry.TriangleMesh, min_fraction: float) -> o3d.t.geometry.TriangleMesh:
    """Remove the connected pieces of ``mesh`` with fewer than ``min_fraction`` of its triangles.

    Depth outliers fused from one or two frames leave small floating pieces
    beside the surface; they carry no surface the other frames agree on.
    The largest piece is always kept; ``min_fraction`` = 0 returns the mesh unchanged.
    """
    if min_fraction <= 0 or "indices" not in mesh.triangle or mesh.triangle.indices.shape[0] == 0:
        return mesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = mesh.triangle.indices.cpu().numpy().astype(np.int64)
    n_vertices = int(mesh.vertex.positions.shape[0])
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    _, label = connected_components(graph, directed=False)
    face_label = label[faces[:, 0]]
    sizes = np.bincount(face_label)
    keep = (sizes[face_label] >= min_fraction * len(faces)) | (face_label == np.argmax(sizes))
    if keep.all():
        return mesh
    return mesh.select_faces_by_mask(o3c.Tensor(keep, device=mesh.device))  # also drops the unused vertices


def _check_trim_rings(rings) -> int:
    if int(rings) < 0:
        raise InputError(f"fusion: boundary_trim_rings must be >= 0, got {rings}",
                         fix="set fusion.boundary_trim_rings=1 (0 keeps the boundary)")
    return int(rings)


def trim_boundary(mesh: o3d.t.geometry.TriangleMesh, rings: int) -> o3d.t.geometry.TriangleMesh:
    """Remove ``rings`` rings of triangles along the open boundary of ``mesh``.

    A triangle touching a boundary vertex (a vertex on an edge used by one triangle) goes, ``rings``
    times over.  Marching cubes closes the surface at the edge of the observed band with triangles
    from voxels that the frames saw only partly or at grazing angles: the least reliable ring of the
    mesh.  A closed surface loses nothing; ``rings`` = 0 returns the mesh unchanged.
    """
    rings = _check_trim_rings(rings)
    if rings == 0 or "indices" not in mesh.triangle or mesh.triangle.indices.shape[0] == 0:
        return mesh
    faces = mesh.triangle.indices.cpu().numpy().astype(np.int64)
    n_vertices = int(mesh.vertex.positions.shape[0])
    keep = np.ones(len(faces), bool)
    for _ in range(rings):
        f = faces[keep]
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        key = edges[:, 0] * n_vertices + edges[:, 1]
        uniq, counts = np.unique(key, return_counts=True)
        border = uniq[counts == 1]
        if len(border) == 0:
            break
        on_border = np.zeros(n_vertices, bool)
        on_border[border // n_vertices] = True
        on_border[border % n_vertices] = True
        idx = np.flatnonzero(keep)
        keep[idx[on_border[f].any(axis=1)]] = False
    if keep.all():
        return mesh
    return mesh.select_faces_by_mask(o3c.Tensor(keep, device=mesh.device))  # also drops the unused vertices


def check_max_std_ratio(ratio) -> float | None:
    """``fusion.max_std_ratio``: None (no uncertainty trim) or a number > 1 (at 1 or below half the mesh would go)."""
    return optional_number_above(ratio, "fusion: max_std_ratio", 1.0,
                                 "set fusion.max_std_ratio=null (keep all surface) or e.g. 2 (drop surface whose fused "
                                 "std is over twice the mesh's median)")


def drop_uncertain(mesh: o3d.t.geometry.TriangleMesh, max_std_ratio: float | None
                   ) -> tuple[o3d.t.geometry.TriangleMesh, dict | None]:
    """Remove the triangles of ``mesh`` with a vertex whose fused ``std`` exceeds ``max_std_ratio`` x the median
    ``std`` of its vertices (unused vertices go too).  The ratio is scale-free, as SfM units are arbitrary.

    Returns the mesh and what was removed (``triangles``, ``removed``, ``median_std``, ``threshold``, ``ratio``);
    the mesh unchanged and None when ``max_std_ratio`` is None, the mesh is empty or has no ``std``.  A median std
    that is not positive says nothing about the surface: nothing is removed then (with a warning)."""
    ratio = check_max_std_ratio(max_std_ratio)
    if ratio is None or "indices" not in mesh.triangle or mesh.triangle.indices.shape[0] == 0 or "std" not in mesh.vertex:
        return mesh, None
    std = mesh.vertex["std"].cpu().numpy().reshape(-1).astype(np.float64)
    faces = mesh.triangle.indices.cpu().numpy().astype(np.int64)
    used = np.unique(faces)
    finite = std[used][np.isfinite(std[used])]  # NaN and inf alike: no fused support, so no say in the median
    median = float(np.median(finite)) if finite.size else float("nan")
    if not (np.isfinite(median) and median > 0):
        log.warning("uncertainty trim skipped: the mesh's median std is %s", median)
        return mesh, dict(triangles=int(len(faces)), removed=0, median_std=median, threshold=float("nan"), ratio=ratio)
    # a vertex without a finite std has no fused support to speak for it
    uncertain = ~np.isfinite(std) | (std > ratio * median)
    keep = ~uncertain[faces].any(axis=1)
    info = dict(triangles=int(len(faces)), removed=int((~keep).sum()), median_std=median, threshold=ratio * median,
                ratio=ratio)
    if keep.all():
        return mesh, info
    return mesh.select_faces_by_mask(o3c.Tensor(keep, device=mesh.device)), info


def median_valid_depth(depth, mask=None) -> float:
    """Median of the finite, positive depths of one (H, W) frame, or of (N, H, W) frames with (N, H, W)
    masks (NaN when none)."""
    d = torch.as_tensor(np.asarray(depth) if not isinstance(depth, torch.Tensor) else depth).float().reshape(-1)
    ok = torch.isfinite(d) & (d > 0)
    if mask is not None:
        m = mask if isinstance(mask, torch.Tensor) else torch.as_tensor(np.asarray(mask))
        ok &= m.reshape(-1).bool()
    return float(d[ok].median()) if bool(ok.any()) else float("nan")


def pixel_band_blocks(depth: torch.Tensor, K: torch.Tensor, cam_from_world: torch.Tensor, trunc: float,
                      block_size: float) -> torch.Tensor:
    """Hash-map blocks that the truncation band of a depth map passes through, at every usable pixel.

    Each pixel with depth z > 0 is walked along its ray from z - trunc to z + trunc (z-depth, as the TSDF
    measures it) in steps of at most a quarter block.

    Args:
        depth: (H, W) z-depth, 0 = unusable.
        K: (3, 3) pixel-centre intrinsics.  cam_from_world: (4, 4).
        trunc: half-width of the band (depth units).  block_size: block edge (voxel size x resolution).
    Returns:
        (M, 3) int32 unique block coordinates (M = 0 when no pixel is usable).
    """
    depth = depth.to(torch.float64).cpu()
    v, u = torch.nonzero(depth > 0, as_tuple=True)
    if len(v) == 0:
        return torch.zeros((0, 3), dtype=torch.int32)
    K, T = K.to(torch.float64).cpu(), cam_from_world.to(torch.float64).cpu()
    rays = unproject(torch.ones_like(depth)[None, None], K[None])[0][:, v, u].T  # (P, 3) at z = 1
    world_from_cam = invert_pose(T[None])[0]
    dirs = rays @ world_from_cam[:3, :3].T  # world ray directions, z-depth 1 each
    n = int(np.ceil(2 * trunc / (0.25 * block_size))) + 1
    offsets = torch.linspace(-trunc, trunc, n, dtype=torch.float64)
    zs = (depth[v, u][:, None] + offsets[None]).clamp_min(0.0)  # (P, n)
    p_world = world_from_cam[:3, 3] + zs[..., None] * dirs[:, None, :]  # (P, n, 3)
    b = torch.floor(p_world.reshape(-1, 3) / block_size).to(torch.int64)
    # unique over one packed int64 key: ~15x faster than a row-wise unique of (P n, 3)
    lo = b.min(0).values
    span = b.max(0).values - lo + 1
    key = torch.unique(((b[:, 0] - lo[0]) * span[1] + (b[:, 1] - lo[1])) * span[2] + (b[:, 2] - lo[2]))
    out = torch.stack([key // (span[1] * span[2]), (key // span[2]) % span[1], key % span[2]], 1) + lo
    return out.to(torch.int32)


class _TSDFBase:
    """Shared frame checks, block activation and mesh saving."""

    attributes: tuple[str, ...] = ()
    channels: tuple[int, ...] = ()
    max_std_ratio: float | None = None  # the uncertainty trim; only AdaptiveTSDF has a std to trim by

    def __init__(self, voxel_size: float, block_resolution: int = 8, block_count: int = 20000,
                 depth_max: float = float("inf"), mesh_weight_threshold: float = 1.0, device: str = "CPU:0",
                 min_component_fraction: float = 0.0, boundary_trim_rings: int = 0, mask_erode_px: int = 0,
                 block_search: str = "sampled", free_space_max_fraction: float | None = None, free_space_tau: float = 0.1,
                 max_nearest_view_ratio: float | None = None):
        self.boundary_trim_rings = _check_trim_rings(boundary_trim_rings)  # before any work, not at saving
        self.free_space_max_fraction, self.free_space_tau = check_free_space_params(free_space_max_fraction, free_space_tau)
        self.max_nearest_view_ratio = check_nearest_view_ratio(max_nearest_view_ratio)
        # the fused frames' full depth (cut-off included: far depth still says "free space up to here"),
        # kept only for the view checks of the saved mesh (free space, nearest view)
        self._seen: list[tuple[torch.Tensor, torch.Tensor | None, np.ndarray, np.ndarray]] = []
        self.last_free_space: dict | None = None
        self.last_uncertain: dict | None = None
        self.last_far_only: dict | None = None
        if block_search not in BLOCK_SEARCHES:
            raise InputError(f"fusion: block_search must be one of {', '.join(BLOCK_SEARCHES)}, got {block_search!r}",
                             fix="set fusion.block_search to every_pixel (every band voxel of a frame is updated) or sampled")
        self.block_search = block_search
        try:
            erode_ok = not isinstance(mask_erode_px, bool) and float(mask_erode_px).is_integer() and mask_erode_px >= 0
        except (TypeError, ValueError):
            erode_ok = False
        if not erode_ok:
            raise InputError(f"fusion: mask_erode_px must be a whole number >= 0, got {mask_erode_px}",
                             fix="set fusion.mask_erode_px to 0 (every pixel of the mask is fused) or a few pixels, e.g. 2")
        self.mask_erode_px = int(mask_erode_px)
        if not 0.0 <= min_component_fraction < 1.0:
            raise InputError(f"fusion: min_component_fraction must be in [0, 1), got {min_component_fraction}",
                             fix="set fusion.min_component_fraction to e.g. 0.01 (0 keeps every piece)")
        self.min_component_fraction = float(min_component_fraction)
        if not (np.isfinite(voxel_size) and voxel_size > 0):
            raise InputError(f"fusion: voxel_size must be a positive number, got {voxel_size}", fix="set fusion.voxel_size or fusion.voxel_fraction")
        if int(block_resolution) < 2:
            raise InputError(f"fusion: block_resolution must be >= 2, got {block_resolution}")
        self.voxel_size = float(voxel_size)
        self.block_resolution = int(block_resolution)
        self.depth_max = float(depth_max)
        self.mesh_weight_threshold = float(mesh_weight_threshold)
        self.device = resolve_device(device)
        self.tdevice = _torch_device(self.device)
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            list(self.attributes), [o3c.float32] * len(self.attributes), list(self.channels),
            self.voxel_size, self.block_resolution, int(block_count), o3c.Device(self.device))
        self.frames = 0

    # ---- input checks --------------------------------------------------
    def _check(self, depth, std, color, K, cam_from_world, mask):
        """Check shapes; return torch float32 depth (H, W), std, color (H, W, 3), bool mask | None, float64 numpy K, T."""
        depth = _as_array(depth, "depth", (2, 3), "(H, W)")
        if depth.ndim == 3:  # tolerate (1, H, W) / (H, W, 1)
            if 1 not in (depth.shape[0], depth.shape[-1]):
                raise InputError(f"fusion: depth has shape {tuple(depth.shape)}, expected (H, W)")
            depth = depth.squeeze(0) if depth.shape[0] == 1 else depth.squeeze(-1)
        H, W = depth.shape
        dev = self.tdevice
        depth = depth.to(dev, torch.float32).contiguous()
        if std is not None:
            std = _as_array(std, "std", (2, 3), "(H, W)")
            _check_map_shape(std, "std", H, W)
            std = std.to(dev, torch.float32).reshape(H, W).contiguous()
        if color is None:
            color = torch.full((H, W, 3), 0.5, dtype=torch.float32, device=dev)
        else:
            color = _as_array(color, "color", 3, "(H, W, 3)")
            if tuple(color.shape) != (H, W, 3):
                raise InputError(f"fusion: color has shape {tuple(color.shape)}, expected {(H, W, 3)} (H, W, 3) in [0, 1]")
            color = (color.to(torch.float32) / 255.0) if color.dtype == torch.uint8 else color
            color = color.to(dev, torch.float32).contiguous()
        if mask is not None:
            mask = _as_array(mask, "mask", (2, 3), "(H, W)")
            _check_map_shape(mask, "mask", H, W)
            mask = mask.reshape(H, W).to(dev).bool().contiguous()
        if self.mask_erode_px > 0:
            full = torch.ones(H, W, dtype=torch.bool, device=dev)
            mask = erode_mask(full if mask is None else mask, self.mask_erode_px).contiguous()
        K = np.asarray(K.detach().cpu() if isinstance(K, torch.Tensor) else K, dtype=np.float64)
        T = np.asarray(cam_from_world.detach().cpu() if isinstance(cam_from_world, torch.Tensor) else cam_from_world,
                       dtype=np.float64)
        if K.shape != (3, 3):
            raise InputError(f"fusion: K has shape {K.shape}, expected (3, 3)")
        if T.shape != (4, 4):
            raise InputError(f"fusion: cam_from_world has shape {T.shape}, expected (4, 4)")
        if not (np.isfinite(K).all() and np.isfinite(T).all()):
            raise InputError("fusion: K or cam_from_world contains NaN/inf (unregistered frame?)", fix="skip frames without a pose")
        return depth, std, color, mask, K, T

    @staticmethod
    def _corner_K(K: np.ndarray) -> np.ndarray:
        # Open3D floors projected pixel coordinates: corner convention (cx, cy + 0.5)
        Kc = K.copy()
        Kc[0, 2] += 0.5
        Kc[1, 2] += 0.5
        return Kc

    @property
    def _o3d_depth_max(self) -> float:
        # Open3D takes a finite depth_max
        return self.depth_max if np.isfinite(self.depth_max) else 1e30

    def _touch_blocks(self, depth: torch.Tensor, K: np.ndarray, T: np.ndarray, trunc_voxels: float,
                      img: o3d.t.geometry.Image | None = None) -> o3c.Tensor:
        """Blocks of the truncation band of a cleaned depth map (0 = unusable), (M, 3) int32.

        ``block_search="every_pixel"`` walks the band at every usable pixel (:func:`pixel_band_blocks`).
        ``"sampled"`` asks Open3D's ``compute_unique_block_coordinates``, which looks at every 4th pixel
        only, so blocks the band crosses between the samples skip the frame while their neighbours take it;
        when it finds no block although the frame has usable pixels (a few pixels left after ``depth_max``),
        it raises, and the band is walked at every pixel then too."""
        if self.block_search == "sampled":
            img = o3d.t.geometry.Image(_o3c_from_torch(depth)) if img is None else img
            try:
                return self.vbg.compute_unique_block_coordinates(
                    img, o3c.Tensor(self._corner_K(K)), o3c.Tensor(T), 1.0, self._o3d_depth_max, float(trunc_voxels))
            except RuntimeError as e:
                if "No block is touched" not in str(e):
                    raise
        bc = pixel_band_blocks(depth, torch.as_tensor(K, dtype=torch.float64), torch.as_tensor(T, dtype=torch.float64),
                               float(trunc_voxels) * self.voxel_size, self.voxel_size * self.block_resolution)
        return _o3c_from_torch(bc.to(self.tdevice).contiguous())

    # ---- mesh ----------------------------------------------------------
    def extract_mesh(self) -> o3d.t.geometry.TriangleMesh:
        """Marching cubes over the voxels observed at least ``mesh_weight_threshold`` times."""
        if self.vbg.hashmap().size() == 0:
            return o3d.t.geometry.TriangleMesh(o3c.Device(self.device))
        # Open3D meshes voxels with weight > threshold; weights count observations (integers),
        # so this meshes voxels observed at least mesh_weight_threshold times
        mesh = self.vbg.extract_triangle_mesh(max(self.mesh_weight_threshold - 0.5, 0.0))
        return drop_small_components(mesh, self.min_component_fraction)

    def save_mesh(self, path: str | Path) -> Path:
        """Extract the mesh, trim ``boundary_trim_rings`` rings off its open boundary and write it to
        ``path`` (PLY, atomically; the header records the trim); returns ``path``.

        With ``free_space_max_fraction`` set, surface that the fused frames see through goes too
        (:meth:`drop_free_space`); with ``max_std_ratio`` set (adaptive fusion), surface whose fused std is over
        that many times the median (:meth:`drop_uncertain`); with ``max_nearest_view_ratio`` set, surface that no
        fused frame sees nearer than that many times their median depth (:meth:`drop_far_only`; after the
        uncertainty trim, whose median std it would otherwise lower); then pieces under
        ``min_component_fraction`` again.  Only the saved product is trimmed and checked: :meth:`extract_mesh`
        (simulated depth, failure detection) keeps it all."""
        mesh = self.drop_free_space(trim_boundary(self.extract_mesh(), self.boundary_trim_rings))
        mesh = self.drop_far_only(self.drop_uncertain(mesh))
        # trimming and the free-space check can split pieces off the surface: the size rule holds for the saved mesh too
        mesh = drop_small_components(mesh, self.min_component_fraction)
        path = Path(path)
        if "indices" not in mesh.triangle or len(mesh.triangle.indices) == 0:
            # an empty file would be skipped as done by the next run and read as "corrupt" by evaluation
            raise InputError("fusion left no surface to save: no voxel was seen by fusion.mesh_weight_threshold "
                             "frames with usable depth and std (or the trims removed it all)", path,
                             "check the depth / std maps and the frames' masks, lower fusion.mesh_weight_threshold, "
                             "or relax fusion.free_space_max_fraction / fusion.max_std_ratio / "
                             "fusion.max_nearest_view_ratio")
        with atomic_path(path) as tmp:
            write_mesh_ply(tmp, mesh, boundary_trim_rings=self.boundary_trim_rings)
        return path

    def _remember(self, depth: torch.Tensor, mask: torch.Tensor | None, K: np.ndarray, T: np.ndarray,
                  std: torch.Tensor | None = None) -> None:
        if self.free_space_max_fraction is not None or self.max_nearest_view_ratio is not None:
            # the caller may reuse its arrays; a frame without a mask keeps every pixel (so that the others' masks
            # still count in the free-space check)
            keep = torch.ones_like(depth, dtype=torch.bool) if mask is None else mask.clone()
            if std is not None:  # a pixel that fusion leaves out for its std does not carve free space either
                keep &= torch.isfinite(std) & (std > 0)
            self._seen.append((depth.clone(), keep, K, T))

    def drop_uncertain(self, mesh: o3d.t.geometry.TriangleMesh) -> o3d.t.geometry.TriangleMesh:
        """``mesh`` without its most uncertain surface (:func:`drop_uncertain`, ``self.max_std_ratio``); a volume
        without std (plain TSDF) keeps it all.  What it removed is in ``self.last_uncertain`` and the log."""
        mesh, self.last_uncertain = drop_uncertain(mesh, self.max_std_ratio)
        if self.last_uncertain and self.last_uncertain["removed"]:
            u = self.last_uncertain
            log.info("uncertainty trim: %d of %d triangles removed (fused std over %.3g = %.3g x the median %.3g)",
                     u["removed"], u["triangles"], u["threshold"], self.max_std_ratio, u["median_std"])
        return mesh

    def drop_free_space(self, mesh: o3d.t.geometry.TriangleMesh) -> o3d.t.geometry.TriangleMesh:
        """``mesh`` without the triangles at vertices that more than ``free_space_max_fraction`` of the fused
        frames see through (:mod:`endorecon.fusion.freespace`); unchanged when the check is off.  What it
        removed is in ``self.last_free_space`` and the log."""
        if self.free_space_max_fraction is None or not self._seen or "indices" not in mesh.triangle:
            return mesh
        n_tri = int(mesh.triangle.indices.shape[0])
        if n_tri == 0:
            return mesh
        on, through, _ = self._surface_views(mesh)
        frac = seen_through_fraction(on, through)
        out = drop_seen_through(mesh, frac, self.free_space_max_fraction)
        left = int(out.triangle.indices.shape[0]) if "indices" in out.triangle else 0
        self.last_free_space = dict(triangles=n_tri, removed=n_tri - left, frames=len(self._seen))
        if left < n_tri:
            log.info("free-space check: %d of %d triangles removed (seen through by more than %.0f%% of the fused frames "
                     "that have them in view; %d frames fused)", n_tri - left, n_tri, 100 * self.free_space_max_fraction,
                     len(self._seen))
        return out

    def _surface_views(self, mesh: o3d.t.geometry.TriangleMesh) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:func:`~endorecon.fusion.freespace.surface_views` of the mesh's vertices in the remembered frames."""
        pos = _torch_view(mesh.vertex.positions).to(torch.float64)
        depth = torch.stack([d for d, _, _, _ in self._seen])
        mask = torch.stack([m for _, m, _, _ in self._seen])
        K = torch.as_tensor(np.stack([k for _, _, k, _ in self._seen]))
        T = torch.as_tensor(np.stack([t for _, _, _, t in self._seen]))
        return surface_views(pos, depth, K, T, mask, self.free_space_tau)

    def median_seen_depth(self) -> float:
        """Median of the remembered frames' finite, positive depth inside their masks (NaN when none)."""
        if not self._seen:
            return float("nan")
        depth = torch.stack([d for d, _, _, _ in self._seen])
        return median_valid_depth(depth, torch.stack([m for _, m, _, _ in self._seen]))

    def drop_far_only(self, mesh: o3d.t.geometry.TriangleMesh) -> o3d.t.geometry.TriangleMesh:
        """``mesh`` without the surface that no fused frame sees nearer than ``max_nearest_view_ratio`` x the fused
        frames' median depth (:func:`~endorecon.fusion.freespace.drop_far_only`; "on its surface" within
        ``free_space_tau``); unchanged when the check is off.  What it removed is in ``self.last_far_only`` and
        the log."""
        if self.max_nearest_view_ratio is None or not self._seen or "indices" not in mesh.triangle \
                or mesh.triangle.indices.shape[0] == 0:
            return mesh
        _, _, nearest = self._surface_views(mesh)
        mesh, self.last_far_only = drop_far_only(mesh, nearest, self.median_seen_depth(), self.max_nearest_view_ratio)
        f = self.last_far_only
        if f and f["removed"]:
            log.info("nearest-view check: %d of %d triangles removed (no fused frame sees them nearer than %.3g = "
                     "%.3g x the median depth %.3g)", f["removed"], f["triangles"], f["threshold"], f["ratio"],
                     f["median_depth"])
        return mesh


class AdaptiveTSDF(_TSDFBase):
    """Adaptive TSDF: std-driven truncation and exponential averaging (Liu et al.).

    Args:
        voxel_size: voxel edge, in the sequence's units.
        c1, c2: bounds of the averaging rate (paper: 0.1, 0.8).
        trunc_std_multiplier: k of the truncation ``clamp(k sigma, m voxel, M voxel)``.
        trunc_min_voxels: m, the floor in voxels (closes holes at grazing angles).
        trunc_max_voxels: M, a cap in voxels (bounds the number of touched blocks).
        depth_max: pixels with a larger depth are ignored.
        block_resolution: voxels per block edge (8 beat 16 on CPU).
        block_count: initial hash-map capacity in blocks (grows as needed).
        mesh_weight_threshold: voxels observed fewer times are not meshed.
        std_mode: voxel std update, ``"propagate"`` (std of the averaged
            estimate) or ``"average"`` (exponential average of the stds); see
            :mod:`endorecon.fusion.kernel`.
        compile: run the per-voxel maths under ``torch.compile(dynamic=True)``;
            falls back to eager (with a warning) if compilation fails.
        device: Open3D device string, ``"CPU:0"``, ``"CUDA:0"`` or ``"auto"``.
        min_component_fraction: mesh pieces with a smaller share of the triangles are dropped.
        boundary_trim_rings: triangle rings trimmed off the open boundary of the saved mesh
            (:func:`trim_boundary`; :meth:`extract_mesh` keeps them).
        mask_erode_px: pixels within this radius of the mask's edge or the image border are not fused
            (:func:`endorecon.fusion.kernel.erode_mask`).
        block_search: ``"sampled"`` or ``"every_pixel"``: how a frame's band finds its blocks (``_touch_blocks``).
        free_space_max_fraction: the saved mesh loses surface that more than this fraction of the fused frames
            see through (:meth:`drop_free_space`); None: no check (and no frame kept for it).
        free_space_tau: relative depth tolerance of that check (:mod:`endorecon.fusion.freespace`).
        max_std_ratio: the saved mesh loses surface whose fused std exceeds this many times the mesh's median
            (:func:`drop_uncertain`); None: all kept.
        max_nearest_view_ratio: the saved mesh loses surface that no fused frame sees nearer than this many times
            the fused frames' median depth (:meth:`drop_far_only`); None: no check.
    """

    attributes = ("tsdf", "weight", "color", "std")
    channels = (1, 1, 3, 1)

    def __init__(self, voxel_size: float, c1: float = 0.1, c2: float = 0.8, trunc_std_multiplier: float = 3.0,
                 trunc_min_voxels: float = 6.0, trunc_max_voxels: float = 24.0, depth_max: float = float("inf"),
                 block_resolution: int = 8, block_count: int = 20000, mesh_weight_threshold: float = 1.0,
                 std_mode: str = "propagate", compile: bool = False, device: str = "CPU:0",
                 min_component_fraction: float = 0.0, boundary_trim_rings: int = 0, mask_erode_px: int = 0,
                 block_search: str = "sampled", free_space_max_fraction: float | None = None, free_space_tau: float = 0.1,
                 max_std_ratio: float | None = None, max_nearest_view_ratio: float | None = None):
        self.max_std_ratio = check_max_std_ratio(max_std_ratio)  # before any work, not at saving
        super().__init__(voxel_size, block_resolution, block_count, depth_max, mesh_weight_threshold, device,
                         min_component_fraction, boundary_trim_rings, mask_erode_px, block_search,
                         free_space_max_fraction, free_space_tau, max_nearest_view_ratio)
        if not (0 < c1 <= c2 <= 1):
            raise InputError(f"fusion: need 0 < c1 <= c2 <= 1, got c1={c1}, c2={c2}", fix="fix fusion.c1 / fusion.c2")
        if not (0 < trunc_min_voxels <= trunc_max_voxels):
            raise InputError(f"fusion: need 0 < trunc_min_voxels <= trunc_max_voxels, got {trunc_min_voxels}, {trunc_max_voxels}")
        if not trunc_std_multiplier > 0:
            raise InputError(f"fusion: trunc_std_multiplier must be > 0, got {trunc_std_multiplier}")
        self.c1, self.c2 = float(c1), float(c2)
        self.k = float(trunc_std_multiplier)
        self.trunc_min = float(trunc_min_voxels) * self.voxel_size
        self.trunc_max = float(trunc_max_voxels) * self.voxel_size
        dmax = self.depth_max if np.isfinite(self.depth_max) else 3.0e38
        if std_mode not in ("propagate", "average"):
            raise InputError(f"fusion: std_mode must be 'propagate' or 'average', got {std_mode!r}")
        self.std_mode = std_mode
        self._params = torch.tensor([self.voxel_size, self.block_resolution, self.c1, self.c2, self.k,
                                     self.trunc_min, self.trunc_max, dmax, float(std_mode == "propagate")],
                                    dtype=torch.float32, device=self.tdevice)
        self._local = local_voxel_offsets(self.block_resolution, torch.float32, self.tdevice)
        self.compile = bool(compile)
        self._clean = _MaybeCompiled(clean_frame, self.compile)
        self._update = _MaybeCompiled(integrate_blocks_, self.compile)
        self.last_rate: torch.Tensor | None = None

    @property
    def compile_seconds(self) -> float | None:
        """Wall time of the first (compiling) calls of the compiled functions; None before / without compile."""
        t = [f.first_call_seconds for f in (self._clean, self._update) if f.first_call_seconds is not None]
        return sum(t) if t else None

    def integrate(self, depth, std, color, K, cam_from_world, mask=None, return_rate: bool = False) -> None:
        """Fuse one frame.

        Args:
            depth: (H, W) z-depth in the sequence's units; NaN/inf/<= 0 ignored.
            std: (H, W) predicted std of the depth (> 0; other pixels ignored).
            color: (H, W, 3) float in [0, 1] (uint8 accepted), or None (grey).
            K: (3, 3) intrinsics, pixel-centre convention.
            cam_from_world: (4, 4).
            mask: (H, W) bool, False = ignore, or None.
            return_rate: keep the applied per-voxel rates in ``self.last_rate``
                (N blocks, R voxels; eager path, for tests and diagnostics).
        """
        if std is None:
            raise InputError("fusion: the adaptive TSDF needs a depth std per pixel", fix="pass std, or use fusion=plain")
        depth, std, color, mask, K, T = self._check(depth, std, color, K, cam_from_world, mask)
        self.frames += 1
        self._remember(depth, mask, K, T, std)
        depth, std, color, widest = self._clean(depth, std, color, mask, self._params)
        widest = float(widest)
        if widest <= 0:  # no usable pixel
            return
        # the touched band must cover the widest truncation of this frame
        bc = self._touch_blocks(depth, K, T, widest / self.voxel_size)
        if bc.shape[0] == 0:
            return
        hm = self.vbg.hashmap()
        new_buf, new_mask = hm.activate(bc)
        buf, _ = hm.find(bc)
        idx = _torch_view(buf).long()
        keys = _torch_view(bc)
        # re-fetch views every frame: activation may have grown (reallocated) the buffers
        R = self.block_resolution ** 3
        tsdf_all = _torch_view(self.vbg.attribute("tsdf")).view(-1, R)
        weight_all = _torch_view(self.vbg.attribute("weight")).view(-1, R)
        std_all = _torch_view(self.vbg.attribute("std")).view(-1, R)
        color_all = _torch_view(self.vbg.attribute("color")).view(-1, R, 3)
        # Open3D does not clear a newly activated block's buffer (a reused slot keeps its old values): the
        # kernel takes weight 0 as "never observed", so a new block must start at zero.
        fresh = _torch_view(new_buf).long()[_torch_view(new_mask).bool()]
        if fresh.numel():
            for a in (tsdf_all, weight_all, std_all, color_all):
                a[fresh] = 0
        Kt = torch.as_tensor(K, dtype=torch.float32, device=self.tdevice)
        Tt = torch.as_tensor(T, dtype=torch.float32, device=self.tdevice)
        if return_rate:
            out = integrate_blocks(keys, tsdf_all[idx], weight_all[idx], std_all[idx], color_all[idx], self._local,
                                   depth, std, color, Kt, Tt, self._params, return_rate=True)
            tsdf_all[idx], weight_all[idx], std_all[idx], color_all[idx], self.last_rate = out
        else:
            self._update(tsdf_all, weight_all, std_all, color_all, idx, keys, self._local, depth, std, color, Kt, Tt, self._params)

    def extract_mesh(self) -> o3d.t.geometry.TriangleMesh:
        """Marching-cubes mesh with vertex ``positions``, ``normals``, ``colors`` (V, 3) in [0, 1] and ``std`` (V, 1).

        Colours and std are interpolated here from the voxels (trilinear over
        observed voxels): Open3D's extraction rescales colours it did not
        integrate itself (it returned colour / 255 on a grid filled from torch).
        """
        mesh = super().extract_mesh()
        if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0:
            return mesh
        pos = _torch_view(mesh.vertex.positions).to(torch.float32)
        vals = self.sample_voxels(pos, ("std", "color"))
        mesh.vertex["std"] = _o3c_from_torch(vals["std"].contiguous())
        mesh.vertex["colors"] = _o3c_from_torch(vals["color"].clamp(0, 1).contiguous())
        return mesh

    def sample_voxels(self, points: torch.Tensor, names=("std",)) -> dict[str, torch.Tensor]:
        """Trilinear interpolation of voxel attributes at ``points`` (N, 3) world.

        Only observed voxels (weight > 0) contribute; NaN where none does.
        Returns ``{name: (N, C)}``.
        """
        r = self.block_resolution
        R = r ** 3
        g = points.to(self.tdevice, torch.float32) / self.voxel_size
        g0 = torch.floor(g)
        f = g - g0
        off = torch.tensor([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)], dtype=torch.float32, device=g.device)
        c = (g0[:, None, :] + off[None]).long()  # (N, 8, 3) voxel grid coords
        w = torch.where(off[None].bool(), f[:, None, :], 1 - f[:, None, :]).prod(-1)  # (N, 8)
        blk = torch.div(c, r, rounding_mode="floor")
        loc = c - blk * r
        buf, found = self.vbg.hashmap().find(_o3c_from_torch(blk.reshape(-1, 3).to(torch.int32)))
        buf = _torch_view(buf).long().reshape(-1, 8)
        found = _torch_view(found).bool().reshape(-1, 8)
        flat = buf.clamp_min(0) * R + loc[..., 0] + r * (loc[..., 1] + r * loc[..., 2])
        flat = torch.where(found, flat, torch.zeros_like(flat))
        wt_all = _torch_view(self.vbg.attribute("weight")).reshape(-1)
        ok = found & (wt_all[flat] > 0)
        w = torch.where(ok, w, torch.zeros_like(w))
        den = w.sum(-1, keepdim=True)
        out = {}
        for name in names:
            a = _torch_view(self.vbg.attribute(name))
            a = a.reshape(-1, a.shape[-1])[flat]  # (N, 8, C)
            s = (w[..., None] * torch.where(ok[..., None], a, torch.zeros_like(a))).sum(1)
            out[name] = torch.where(den > 0, s / den.clamp_min(1e-12), torch.full_like(s, float("nan")))
        return out


def _check_map_shape(x: torch.Tensor, name: str, H: int, W: int) -> None:
    """(H, W), (1, H, W) or (H, W, 1): a (W, H) map has as many elements but would be scrambled by a reshape."""
    if tuple(x.shape) not in ((H, W), (1, H, W), (H, W, 1)):
        raise InputError(f"fusion: {name} has shape {tuple(x.shape)}, depth is {(H, W)}",
                         fix=f"pass {name} as (H, W) like depth")


class PlainTSDF(_TSDFBase):
    """Baseline: Open3D's ``VoxelBlockGrid.integrate`` (truncation ``trunc_voxels`` voxels, running average).

    Same interface as :class:`AdaptiveTSDF`; ``std`` is ignored.
    """

    attributes = ("tsdf", "weight", "color")
    channels = (1, 1, 3)

    def __init__(self, voxel_size: float, trunc_voxels: float = 6.0, depth_max: float = float("inf"),
                 block_resolution: int = 8, block_count: int = 20000, mesh_weight_threshold: float = 1.0,
                 device: str = "CPU:0", min_component_fraction: float = 0.0, boundary_trim_rings: int = 0,
                 mask_erode_px: int = 0, block_search: str = "sampled", free_space_max_fraction: float | None = None,
                 free_space_tau: float = 0.1, max_nearest_view_ratio: float | None = None):
        super().__init__(voxel_size, block_resolution, block_count, depth_max, mesh_weight_threshold, device,
                         min_component_fraction, boundary_trim_rings, mask_erode_px, block_search,
                         free_space_max_fraction, free_space_tau, max_nearest_view_ratio)
        if not trunc_voxels > 0:
            raise InputError(f"fusion: trunc_voxels must be > 0, got {trunc_voxels}")
        self.trunc_voxels = float(trunc_voxels)
        dmax = self.depth_max if np.isfinite(self.depth_max) else 3.0e38
        t = self.trunc_voxels * self.voxel_size
        self._params = torch.tensor([self.voxel_size, self.block_resolution, 0, 0, 0, t, t, dmax, 0],
                                    dtype=torch.float32, device=self.tdevice)

    def integrate(self, depth, std, color, K, cam_from_world, mask=None) -> None:
        """Fuse one frame (arguments as :meth:`AdaptiveTSDF.integrate`; ``std`` is ignored)."""
        depth, _, color, mask, K, T = self._check(depth, None, color, K, cam_from_world, mask)
        self.frames += 1
        self._remember(depth, mask, K, T)
        depth, _, color, widest = clean_frame(depth, None, color, mask, self._params)
        if float(widest) <= 0:
            return
        bc = self._touch_blocks(depth, K, T, self.trunc_voxels, o3d.t.geometry.Image(_o3c_from_torch(depth)))
        if bc.shape[0] == 0:
            return
        # Open3D's bound check takes u <= W-1 in corner coordinates, so the last column / row (u in [W-1, W)) was
        # never fused, and column / row 0 came back at u = -1e-7 from its unproject-project round trip, which
        # fused depth without colour.  One pixel of padding all round (no depth; edge colour) and the principal
        # point moved with it fuse every pixel, each with its colour.
        depth_p = torch.nn.functional.pad(depth[None, None], (1, 1, 1, 1))[0, 0].contiguous()
        color_p = torch.nn.functional.pad(color.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0]
        color_p = color_p.permute(1, 2, 0).contiguous()
        K_p = K.copy()
        K_p[0, 2] += 1.0
        K_p[1, 2] += 1.0
        Kc = o3c.Tensor(self._corner_K(K_p))
        self.vbg.integrate(bc, o3d.t.geometry.Image(_o3c_from_torch(depth_p)),
                           o3d.t.geometry.Image(_o3c_from_torch(color_p)), Kc, Kc, o3c.Tensor(T), 1.0,
                           self._o3d_depth_max, self.trunc_voxels)


class _MaybeCompiled:
    """``torch.compile(fn, dynamic=True)`` made lazily on first call, with an eager fallback.

    Compiled functions are shared between instances (one compile per process);
    ``first_call_seconds`` is the wall time of this instance's first call.
    """

    _cache: dict = {}

    def __init__(self, fn, enabled: bool):
        self.fn = fn
        self.enabled = enabled
        self.impl = None if enabled else fn
        self.first_call_seconds: float | None = None

    def __call__(self, *args):
        if self.impl is None:
            try:
                if self.fn not in self._cache:
                    self._cache[self.fn] = torch.compile(self.fn, dynamic=True)
                self.impl = self._cache[self.fn]
            except Exception as e:  # noqa: BLE001 - no dynamo on this platform -> eager
                warnings.warn(f"torch.compile unavailable ({type(e).__name__}: {e}); using eager torch")
                self.impl = self.fn
        if self.first_call_seconds is not None or self.impl is self.fn and not self.enabled:
            return self.impl(*args)
        t0 = time.perf_counter()
        try:
            out = self.impl(*args)
        except Exception as e:  # noqa: BLE001 - any compiler failure -> eager
            if self.impl is self.fn:
                raise
            warnings.warn(f"torch.compile of {self.fn.__name__} failed ({type(e).__name__}: {e}); using eager torch")
            self.impl = self.fn
            out = self.fn(*args)
        self.first_call_seconds = time.perf_counter() - t0
        return out

"""Ray-cast rendering of triangle meshes with Open3D's ``RaycastingScene``.

:class:`MeshRenderer` casts one ray per pixel of a pinhole camera and returns
the z-depth, the triangle hit, its barycentric coordinates, interpolated vertex
normals and the world points.  :func:`render_depth` renders z-depth for many
poses at once: the bootstrapping loop uses it to turn a fused mesh into
"simulated depth" at every frame's pose; the phantom uses it for ground truth.

Conventions: ``K`` is pixel-centre (pixel (0, 0) is the centre of the top-left
pixel, as :mod:`endorecon.geometry`); ``cam_from_world`` maps world to camera
(x_cam = R x_world + t).  Rays are built here from ``K`` directly with camera
direction ``K^-1 (u, v, 1)``, i.e. unit z component, so Open3D's ``t_hit`` is
the z-depth (not the ray length) and no corner-convention shift is needed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from endorecon.utils.errors import InputError

__all__ = ["MeshRenderer", "render_depth", "load_mesh_arrays", "pixel_rays_cam"]


def load_mesh_arrays(mesh: Any) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and triangles (F, 3) int64 of a mesh given in any supported form.

    ``mesh``: a PLY/OBJ/... path, an open3d legacy or tensor ``TriangleMesh``,
    or a ``(vertices (V, 3), triangles (F, 3))`` pair of arrays.
    """
    import open3d as o3d

    if isinstance(mesh, (str, Path)):
        path = Path(mesh)
        if not path.is_file():
            raise InputError("mesh file does not exist", path, "pass a triangle mesh file (PLY, OBJ, STL)")
        m = o3d.io.read_triangle_mesh(str(path))
        if len(m.triangles) == 0:
            raise InputError("mesh file has no triangles (unreadable or a point cloud)", path, "pass a triangle mesh")
        return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64)
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)
    if isinstance(mesh, o3d.t.geometry.TriangleMesh):
        return (
            mesh.vertex.positions.cpu().numpy().astype(np.float64),  # fusion on CUDA:0 gives a device mesh
            mesh.triangle.indices.cpu().numpy().astype(np.int64),
        )
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        v = np.asarray(mesh[0], dtype=np.float64)
        f = np.asarray(mesh[1], dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise InputError(f"mesh arrays must be vertices (V,3) and triangles (F,3), got {v.shape} and {f.shape}")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise InputError("triangle indices out of range of the vertices")
        return v, f
    raise InputError(f"unsupported mesh type {type(mesh).__name__}", fix="pass a path, an open3d TriangleMesh or (V, F)")


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) following the triangles' winding."""
    v0, v1, v2 = (vertices[triangles[:, k]] for k in range(3))
    fn = np.cross(v1 - v0, v2 - v0)  # length = 2 * area: area weighting for free
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, triangles[:, k], fn)
    n = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.maximum(n, 1e-30)


def pixel_rays_cam(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Camera-frame ray directions (H, W, 3) with z = 1 through every pixel centre (pixel-centre K)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    fx, fy, cx, cy, s = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    y = (vv - cy) / fy
    x = (uu - cx - s * y) / fx
    return np.stack([x, y, np.ones_like(x)], axis=-1)


class MeshRenderer:
    """Ray caster for one static triangle mesh.

    Args:
        mesh: PLY path, open3d legacy/tensor ``TriangleMesh``, or ``(vertices, triangles)`` arrays.
        n_threads: threads for Open3D's ray casting (0 = all cores).
    """

    def __init__(self, mesh: Any, n_threads: int = 0):
        import open3d as o3d

        self.vertices, self.triangles = load_mesh_arrays(mesh)
        if len(self.triangles) == 0:
            raise InputError("mesh has no triangles", fix="pass a non-empty triangle mesh")
        self.normals = vertex_normals(self.vertices, self.triangles)
        self._normals32 = self.normals.astype(np.float32)
        self._corner_normals32 = self._normals32[self.triangles]  # (T, 3 corners, 3): one gather per render
        self.n_threads = int(n_threads)
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)), o3d.core.Tensor(self.triangles.astype(np.uint32))
        )
        self._ray_cache: dict[tuple, np.ndarray] = {}

    # ------------------------------------------------------------------ rays
    def _rays_cam(self, K: np.ndarray, height: int, width: int) -> np.ndarray:
        key = (tuple(np.asarray(K, dtype=np.float64).ravel()), int(height), int(width))
        rays = self._ray_cache.get(key)
        if rays is None:
            if len(self._ray_cache) > 8:
                self._ray_cache.clear()
            rays = pixel_rays_cam(K, height, width)
            self._ray_cache[key] = rays
        return rays

    def _world_rays(self, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int) -> np.ndarray:
        """(..., H, W, 6) float32 rays [origin, direction] in world coordinates for (..., 4, 4) poses."""
        d_cam = self._rays_cam(K, height, width)
        T = np.asarray(cam_from_world, dtype=np.float64)
        R = T[..., :3, :3]
        t = T[..., :3, 3]
        # world_from_cam: x_w = R^T (x_c - t); centre = -R^T t; direction = R^T d
        centre = -np.einsum("...ji,...j->...i", R, t)
        # one pose: a BLAS matmul (x2.7 faster than the einsum, the same float32 rays on the phantom's views)
        d_world = d_cam @ R if R.ndim == 2 else np.einsum("...ji,hwj->...hwi", R, d_cam)
        lead = T.shape[:-2]
        rays = np.empty(lead + (height, width, 6), dtype=np.float32)
        rays[..., :3] = centre[..., None, None, :]
        rays[..., 3:] = d_world
        return rays

    def cast(self, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int) -> dict[str, np.ndarray]:
        """Raw cast for poses (..., 4, 4): ``t_hit`` (z-depth, inf on miss), ``primitive_ids``, ``primitive_uvs``."""
        rays = self._world_rays(K, cam_from_world, height, width)
        out = self.scene.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.n_threads)
        return {
            "t_hit": out["t_hit"].numpy(),
            "primitive_ids": out["primitive_ids"].numpy(),
            "primitive_uvs": out["primitive_uvs"].numpy(),
        }

    # ---------------------------------------------------------------- render
    def render(self, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int) -> dict[str, np.ndarray]:
        """Render one view.

        Args:
            K: (3, 3) pixel-centre intrinsics.
            cam_from_world: (4, 4) pose.
            height, width: image size.
        Returns:
            dict with ``depth`` (H, W) float32 z-depth (0 = no hit), ``hit`` (H, W) bool,
            ``triangle_ids`` (H, W) int64 (-1 = miss), ``uvs`` (H, W, 2) float32 barycentric
            (p = (1-u-v) v0 + u v1 + v v2), ``normals_world`` (H, W, 3) float32 interpolated unit
            vertex normals (0 on miss), ``points_world`` (H, W, 3) float32 (0 on miss).
        """
        T = _check_pose(cam_from_world, single=True)
        rays = self._world_rays(K, T, height, width)
        raw = self.scene.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.n_threads)
        t = raw["t_hit"].numpy()
        hit = np.isfinite(t)
        ids = raw["primitive_ids"].numpy().astype(np.int64)
        ids[~hit] = -1
        uvs = raw["primitive_uvs"].numpy()
        uvs[~hit] = 0
        depth = np.where(hit, t, np.float32(0))
        # whole-image arithmetic (a view inside a cavity hits almost everywhere: masking costs more)
        u, v = uvs[..., 0:1], uvs[..., 1:2]
        vn = self._corner_normals32[np.where(hit, ids, 0)]  # (H, W, 3 corners, 3)
        # (1-u-v) n0 + u n1 + v n2, summed in that order into one buffer (fewer full-image temporaries)
        normals = (1.0 - u - v) * vn[..., 0, :]
        term = u * vn[..., 1, :]
        normals += term
        np.multiply(v, vn[..., 2, :], out=term)
        normals += term
        normals *= (hit / np.maximum(np.linalg.norm(normals, axis=-1), 1e-12))[..., None]
        # the hit point along the ray (z-depth times the z = 1 direction): the barycentric point
        # up to float32 rounding, and cheaper
        points = rays[..., :3] * hit[..., None] + depth[..., None] * rays[..., 3:]
        return {"depth": depth, "hit": hit, "triangle_ids": ids, "uvs": uvs, "normals_world": normals, "points_world": points}

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned point-to-mesh distance (N,) float64 for points (N, 3)."""
        p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        return self.scene.compute_distance(self._o3d.core.Tensor(p), nthreads=self.n_threads).numpy().astype(np.float64)

    def occupancy(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: inside the closed surface (meaningful for watertight meshes only)."""
        p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        return self.scene.compute_occupancy(self._o3d.core.Tensor(p), nthreads=self.n_threads).numpy() > 0.5


def _check_pose(cam_from_world: np.ndarray, single: bool) -> np.ndarray:
    T = np.asarray(cam_from_world, dtype=np.float64)
    if single and T.shape != (4, 4):
        raise ValueError(f"cam_from_world must be (4, 4), got {T.shape}")
    if not single and (T.ndim != 3 or T.shape[1:] != (4, 4)):
        raise ValueError(f"cam_from_world must be (N, 4, 4), got {T.shape}")
    return T


def render_depth(
    mesh_or_renderer: Any,
    K: Any,
    cam_from_world: Any,
    height: int,
    width: int,
    mask: Any = None,
    chunk: int = 16,
):
    """Render z-depth of a mesh at many poses.

    Args:
        mesh_or_renderer: a :class:`MeshRenderer` or anything it accepts.
        K: (3, 3) or (N, 3, 3) pixel-centre intrinsics.
        cam_from_world: (N, 4, 4) poses; frames whose pose or K has a non-finite entry come back all invalid.
        height, width: image size.
        mask: optional (H, W) or (N, H, W) bool valid-pixel mask (False pixels are invalid).
        chunk: frames cast per Open3D call.
    Returns:
        depth (N, H, W) float32 z-depth (0 where invalid), valid (N, H, W) bool.
        numpy arrays, or torch tensors (on ``cam_from_world``'s device) if ``cam_from_world`` is a tensor.
    """
    as_torch = False
    device = None
    if hasattr(cam_from_world, "detach"):  # torch tensor, without importing torch for numpy users
        as_torch, device = True, cam_from_world.device
    T = _check_pose(_to_numpy(cam_from_world), single=False)
    n = len(T)
    Ks = np.asarray(_to_numpy(K), dtype=np.float64)
    if Ks.shape == (3, 3):
        Ks = np.broadcast_to(Ks, (n, 3, 3))
    if Ks.shape != (n, 3, 3):
        raise ValueError(f"K must be (3, 3) or ({n}, 3, 3), got {Ks.shape}")
    m = None
    if mask is not None:
        m = np.asarray(_to_numpy(mask)).astype(bool)
        if m.ndim == 4 and m.shape[1] == 1:  # (N, 1, H, W) project convention
            m = m[:, 0]
        if m.shape not in ((height, width), (n, height, width)):
            raise ValueError(f"mask must be (H, W) or (N, H, W) = ({n}, {height}, {width}), got {m.shape}")
    renderer = mesh_or_renderer if isinstance(mesh_or_renderer, MeshRenderer) else MeshRenderer(mesh_or_renderer)

    depth = np.zeros((n, height, width), np.float32)
    finite = np.isfinite(T).all(axis=(1, 2)) & np.isfinite(Ks).all(axis=(1, 2))
    idx = np.flatnonzero(finite)
    same_k = bool(np.all(Ks[idx] == Ks[idx[:1]])) if len(idx) else True
    if same_k:
        for s in range(0, len(idx), chunk):
            sel = idx[s : s + chunk]
            t = renderer.cast(Ks[sel[0]], T[sel], height, width)["t_hit"]
            depth[sel] = np.where(np.isfinite(t), t, 0)
    else:
        for i in idx:
            t = renderer.cast(Ks[i], T[i], height, width)["t_hit"]
            depth[i] = np.where(np.isfinite(t), t, 0)
    valid = depth > 0
    if m is not None:
        valid &= m if m.ndim == 3 else m[None]
        depth[~valid] = 0
    if as_torch:
        import torch

        return torch.from_numpy(depth).to(device), torch.from_numpy(valid).to(device)
    return depth, valid


def _to_numpy(x: Any) -> Any:
    if hasattr(x, "detach"):
        return x.detach().cpu().numpy()
    return x

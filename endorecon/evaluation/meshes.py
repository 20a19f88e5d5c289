"""Mesh loading with user-facing errors, area-uniform sampling, and the reference surface.

The reference ("CT") surface wraps an Open3D ``RaycastingScene`` so that exact
closest points, face normals and point-to-surface distances come from one BVH.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from endorecon.utils.errors import InputError

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")


def load_mesh(path: str | Path, what: str = "mesh") -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh; raise :class:`InputError` naming the file if it is missing, corrupt or empty.

    Args:
        path: a mesh file (ply/obj/stl/off/gltf/glb).
        what: how to call the file in messages ("reconstructed mesh", "reference mesh").
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file is missing", path, "check the path (mesh=..., reference=...)")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(
            f"{what} has an unsupported extension '{path.suffix}'", path, f"give a mesh file ({', '.join(MESH_SUFFIXES)})"
        )
    if path.stat().st_size == 0:
        raise InputError(f"{what} file is empty (0 bytes)", path, "re-create the mesh")
    try:
        mesh = o3d.io.read_triangle_mesh(str(path))
    except Exception as e:  # open3d raises on some malformed files, returns an empty mesh on others
        raise InputError(f"{what} could not be read: {e}", path, "re-create the mesh") from e
    if len(mesh.vertices) == 0:
        raise InputError(f"{what} is corrupt or has no vertices", path, "re-create the mesh")
    if len(mesh.triangles) == 0:
        raise InputError(
            f"{what} has no triangles (a point cloud?)", path, "give a triangle mesh (e.g. the fused mesh.ply)"
        )
    v = np.asarray(mesh.vertices)
    if not np.isfinite(v).all():
        raise InputError(f"{what} has non-finite vertex coordinates", path, "re-create the mesh")
    tri = np.asarray(mesh.triangles)
    if tri.min() < 0 or tri.max() >= len(v):
        raise InputError(f"{what} has triangle indices out of range", path, "re-create the mesh")
    if _triangle_areas(v, tri).sum() <= 0:
        raise InputError(f"{what} has zero surface area (all triangles degenerate)", path, "re-create the mesh")
    return mesh


def _triangle_areas(v: np.ndarray, tri: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]), axis=1)


# Recorded with every evaluation, so that one made by an earlier sampler (stored order) is not reused.
SAMPLER = "area-uniform, coordinate order"


def sample_points(mesh: o3d.geometry.TriangleMesh, n: int = 40000, seed: int = 0) -> np.ndarray:
    """Area-uniform random points on a triangle mesh.

    Done in numpy rather than ``sample_points_uniformly`` so that the result
    depends on ``seed`` only (Open3D's sampler uses a global generator), and on the
    surface, not on the order it is stored in: the fusion's hash map lists blocks in
    an order that varies with threads, so the same mesh comes out with its vertices and
    triangles permuted, and sampling in stored order made its residuals differ (0.03 mm
    in mean on a debug mesh).

    Returns:
        points: (n, 3) float64, in the mesh's units.
    """
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    tri = _canonical_triangles(v, np.asarray(mesh.triangles))
    area = _triangle_areas(v, tri)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    # Uniform barycentrics: fold the unit square onto the triangle.
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    v0, v1, v2 = (v[tri[face, k]] for k in range(3))
    return v0 + a[:, None] * (v1 - v0) + b[:, None] * (v2 - v0)


def _canonical_triangles(v: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """tri (T,3) in an order set by the coordinates alone: each triangle rotated (orientation kept)
    to start at its lexicographically smallest vertex, triangles sorted by their vertices."""
    if len(tri) == 0:
        return tri
    rank = np.empty(len(v), dtype=np.int64)
    rank[np.lexsort((v[:, 2], v[:, 1], v[:, 0]))] = np.arange(len(v))
    r = rank[tri]
    shift = np.argmin(r, axis=1)[:, None]
    cyc = (shift + np.arange(3)[None, :]) % 3
    tri = np.take_along_axis(tri, cyc, axis=1)
    r = np.take_along_axis(r, cyc, axis=1)
    return tri[np.lexsort((r[:, 2], r[:, 1], r[:, 0]))]


class ReferenceSurface:
    """Closest points and distances to a triangle mesh (the "CT" surface), via one Open3D BVH.

    Open3D's scene works in float32: coordinates of ~100 mm keep ~1e-5 mm.
    """

    def __init__(self, mesh: o3d.geometry.TriangleMesh):
        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """points: (N, 3) -> (closest points (N, 3), unit face normals there (N, 3)), float64."""
        _check_points(points)
        r = self.scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32)))
        return r["points"].numpy().astype(np.float64), r["primitive_normals"].numpy().astype(np.float64)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned point-to-surface distance.  points: (N, 3) -> (N,) float64."""
        _check_points(points)
        pts = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        return self.scene.compute_distance(pts).numpy().astype(np.float64)


def _check_points(points: np.ndarray) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")

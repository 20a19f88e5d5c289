"""Evaluate a reconstructed mesh against a reference ("CT") mesh in millimetres.

``evaluate_mesh``: sample points on the reconstruction, register them to the
reference with a similarity (see ``registration``), measure point-to-surface
distances of the registered samples, and write ``metrics.json``,
``residual_heatmap.png``, ``residual_histogram.png`` and ``residuals.npz``
(registered samples + their distances).  Residuals are in the reference's
units, which are millimetres for CT / the phantom.  When the mesh carries
endorecon's per-vertex ``std``, ``metrics.json`` also says how well that std
ranks the vertices' residuals (``std_residual_spearman``), so an uncertainty
that does not point at the errors shows in every evaluation.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from endorecon.evaluation.meshes import SAMPLER, ReferenceSurface, load_mesh, sample_points
from endorecon.evaluation.plots import save_residual_heatmap, save_residual_histogram
from endorecon.evaluation.registration import register
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_save_npz, atomic_write_text, file_id

METRICS_FILE = "metrics.json"
HEATMAP_FILE = "residual_heatmap.png"
HISTOGRAM_FILE = "residual_histogram.png"
RESIDUALS_FILE = "residuals.npz"
GLOBAL_POINTS = 20000  # samples per mesh for the FPFH + RANSAC initialisation
# Recorded with every evaluation: metrics of an earlier version (without the std ranking) are not reused.
METRICS_VERSION = 4  # 3: area_mm2 and ct_covered_mm2; 4: the CT behind holes is not covered
# a CT point counts as reconstructed when the registered mesh passes within this distance (mm)
COVERAGE_MM = 1.0


def vertex_std(mesh_path: Path, vertices: np.ndarray) -> np.ndarray | None:
    """Per-vertex ``std`` of a mesh written by endorecon's fusion, in the order of ``vertices`` (V, 3) as
    :func:`load_mesh` read them; None when the file has no std (any other mesh) or its vertices differ."""
    from endorecon.fusion.ply import read_mesh_ply

    try:
        tm = read_mesh_ply(mesh_path)
    except Exception:  # not one of endorecon's PLYs: no std to rank
        return None
    if "std" not in tm.vertex:
        return None
    pos = tm.vertex.positions.numpy().astype(np.float64)
    if pos.shape != vertices.shape or not np.allclose(pos, vertices, rtol=0, atol=1e-6 * max(1.0, np.abs(pos).max())):
        return None
    return tm.vertex["std"].numpy().reshape(-1).astype(np.float64)


def _finite_or_null(x):
    """NaN / inf (no JSON value) as null, e.g. a registration diagnostic of an empty inlier set."""
    if isinstance(x, dict):
        return {k: _finite_or_null(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_null(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def residual_stats(residual_mm: np.ndarray) -> dict:
    """Summary of point-to-surface distances.  residual_mm: (N,) -> mean/median/p95/max/rmse in mm, frac < 1 mm."""
    r = np.asarray(residual_mm, dtype=np.float64)
    if r.ndim != 1 or len(r) == 0:
        raise ValueError(f"residual_mm must be a non-empty (N,), got {r.shape}")
    if not np.isfinite(r).all():
        raise ValueError(f"{int((~np.isfinite(r)).sum())} of {len(r)} residuals are not finite")
    return {
        "mean_mm": float(r.mean()),
        "median_mm": float(np.median(r)),
        "p95_mm": float(np.percentile(r, 95)),
        "max_mm": float(r.max()),
        "rmse_mm": float(np.sqrt((r**2).mean())),
        "frac_below_1mm": float((r < 1.0).mean()),
        "n_points": int(len(r)),
    }


def _fingerprint(mesh_path: Path, reference_path: Path, arrays: tuple, params: dict) -> dict:
    h = hashlib.sha1()
    for a in arrays:
        h.update(b"none" if a is None else np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return {"mesh": file_id(mesh_path), "reference": file_id(reference_path), "trajectory_sha1": h.hexdigest(), **params}


def coverage(recon_registered: o3d.geometry.TriangleMesh, reference: o3d.geometry.TriangleMesh,
             n_points: int = 40000, seed: int = 0, within_mm: float = COVERAGE_MM) -> dict:
    """Surface area of the registered reconstruction and of the reference it covers, in mm².

    ``ct_covered_mm2``: the reference's area whose points lie within ``within_mm`` of the reconstruction, their
    closest point not on its open boundary (``n_points`` area-uniform samples): the CT behind a hole in the mesh
    is not covered, however narrow the hole (by distance alone a 2 mm hole counted as covered, and every border
    added a band); ``ct_area_mm2``: the whole reference (a video sees part of it).
    """
    samples = sample_points(reference, n_points, seed + 3)
    near = _covered(recon_registered, samples, within_mm)
    ct_area = float(reference.get_surface_area())
    return {"area_mm2": float(recon_registered.get_surface_area()), "ct_area_mm2": ct_area,
            "ct_covered_mm2": ct_area * float(near.mean()), "coverage_within_mm": float(within_mm)}


def _covered(mesh: o3d.geometry.TriangleMesh, points: np.ndarray, within: float, eps: float = 1e-4) -> np.ndarray:
    """(N,) bool: the closest point of ``mesh`` to each point is within ``within`` and not on its open boundary
    (an edge of one triangle, or a vertex of such an edge)."""
    tri = np.asarray(mesh.triangles, dtype=np.int64)
    if len(tri) == 0:
        return np.zeros(len(points), bool)
    r = ReferenceSurface(mesh).scene.compute_closest_points(
        o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32)))
    q = r["points"].numpy().astype(np.float64)
    ids = r["primitive_ids"].numpy().astype(np.int64)
    uv = r["primitive_uvs"].numpy().astype(np.float64)
    near = np.linalg.norm(q - points, axis=1) <= within
    n_v = len(mesh.vertices)
    edges = np.sort(np.concatenate([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]]), axis=1)
    keys, counts = np.unique(edges[:, 0] * n_v + edges[:, 1], return_counts=True)
    open_keys = keys[counts == 1]
    if len(open_keys) == 0:  # a closed mesh
        return near
    open_vertex = np.zeros(n_v, bool)
    open_vertex[open_keys // n_v] = True
    open_vertex[open_keys % n_v] = True
    t = tri[ids]
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)  # weights of t's corners 0, 1, 2
    on_open = np.zeros(len(points), bool)
    for k, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):  # weight k ~ 0: on the edge opposite corner k
        e = np.sort(t[:, [a, b]], axis=1)
        on_open |= (bary[:, k] < eps) & np.isin(e[:, 0] * n_v + e[:, 1], open_keys)
    at_vertex = (bary < eps).sum(axis=1) >= 2  # a corner: open if it lies on any open edge
    corner = t[np.arange(len(t)), np.argmax(bary, axis=1)]
    on_open |= at_vertex & open_vertex[corner]
    return near & ~on_open


def evaluate_mesh(
    mesh_path: str | Path,
    reference_path: str | Path,
    out_dir: str | Path,
    cam_centers: np.ndarray | None = None,
    gt_cam_centers: np.ndarray | None = None,
    n_points: int = 40000,
    seed: int = 0,
    registration: dict | None = None,
    *,
    cam_rotations: np.ndarray | None = None,
    gt_cam_rotations: np.ndarray | None = None,
    heatmap_views: int = 3,
    vmax_mm: float | None = None,
    overwrite: bool = False,
) -> dict:
    """Register a reconstruction to a reference surface and measure residuals in mm.

    Args:
        mesh_path: reconstructed mesh (any scale).
        reference_path: reference surface in millimetres.
        out_dir: where ``metrics.json`` and the PNGs go.
        cam_centers, gt_cam_centers: (K, 3) camera centres of the same K frames in the
            reconstruction's and the reference's frame; when given they initialise the registration.
        cam_rotations, gt_cam_rotations: optional (K, 3, 3) ``cam_from_world`` rotations of those
            frames; they fix the roll when the trajectory is nearly a straight line.
        n_points: samples on the reconstruction.
        registration: options of :func:`endorecon.evaluation.registration.register`
            (init, global_trials, global_voxel_frac, and ICP options max_iter, reject_k, max_dist,
            point_weight).
        overwrite: recompute even if ``metrics.json`` for the same inputs exists.
    Returns:
        the metrics dict written to ``metrics.json``: residual statistics (:func:`residual_stats`), the
        similarity, the registration's diagnostics and ``std_residual_spearman`` (Spearman ρ of the mesh's
        per-vertex std against the vertices' residuals; None when the mesh has no std or it is constant).
    Raises:
        InputError: a mesh is missing, corrupt, empty or has no triangles.
    """
    t_start = time.perf_counter()
    mesh_path, reference_path, out_dir = Path(mesh_path), Path(reference_path), Path(out_dir)
    recon = load_mesh(mesh_path, "reconstructed mesh")
    reference = load_mesh(reference_path, "reference mesh")
    registration = dict(registration or {})
    params = {"n_points": int(n_points), "seed": int(seed), "sampler": SAMPLER, "registration": registration,
              "metrics_version": METRICS_VERSION, "vmax_mm": vmax_mm, "heatmap_views": heatmap_views}
    inputs = _fingerprint(
        mesh_path, reference_path, (cam_centers, gt_cam_centers, cam_rotations, gt_cam_rotations), params
    )
    metrics_path = out_dir / METRICS_FILE
    if not overwrite and metrics_path.is_file() and all((out_dir / f).is_file()
                                                        for f in (HEATMAP_FILE, HISTOGRAM_FILE, RESIDUALS_FILE)):
        try:
            old = json.loads(metrics_path.read_text())
        except json.JSONDecodeError:
            old = {}
        if old.get("inputs") == json.loads(json.dumps(inputs)):
            return old

    points = sample_points(recon, n_points, seed)
    surface = ReferenceSurface(reference)
    init = registration.get("init", "auto")
    needs_global = init == "global" or (init == "auto" and (cam_centers is None or gt_cam_centers is None))
    ref_points = global_src = None
    if needs_global:  # FPFH wants dense clouds whatever n_points is
        ref_points = sample_points(reference, max(n_points, GLOBAL_POINTS), seed + 1)
        global_src = points if n_points >= GLOBAL_POINTS else sample_points(recon, GLOBAL_POINTS, seed + 2)
    fix = ("check trajectory= / gt_trajectory= (camera centres that all coincide give no scale), or leave them out "
           "for the global registration")
    try:
        res = register(
            points, surface, ref_points=ref_points, global_src_points=global_src, cam_centers=cam_centers,
            gt_cam_centers=gt_cam_centers, cam_rotations=cam_rotations, gt_cam_rotations=gt_cam_rotations, seed=seed,
            **registration,
        )
    except ValueError as e:  # degenerate trajectories (umeyama), a non-finite initialisation
        raise InputError(f"the registration found no similarity: {e}", mesh_path, fix) from e
    T = res.ref_from_recon
    if not np.isfinite(T.matrix()).all() or not T.scale > 0:
        raise InputError(f"the registration gave no usable similarity (scale {T.scale}, init {res.init})", mesh_path,
                         fix)
    registered = T.apply(points)
    residual = surface.distance(registered)

    metrics = residual_stats(residual)
    metrics["sim3"] = T.to_dict()
    metrics["registration"] = res.to_dict()
    metrics["units"] = "reference units (mm for CT / phantom)"

    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_save_npz(out_dir / RESIDUALS_FILE, points_registered=registered.astype(np.float32),
                    residual_mm=residual.astype(np.float32))
    recon_reg = o3d.geometry.TriangleMesh(recon)
    recon_reg.vertices = o3d.utility.Vector3dVector(T.apply(np.asarray(recon.vertices, dtype=np.float64)))
    vertex_residual = surface.distance(np.asarray(recon_reg.vertices))
    # How much anatomy the residuals are about: trimming a mesh lowers its residuals by covering less, so
    # the mesh's area and the CT area it reconstructs are reported beside them.
    metrics.update(coverage(recon_reg, reference, n_points, seed))
    # Does the mesh's own uncertainty point at its errors? Rank correlation over the vertices (NaN: constant std).
    std = vertex_std(mesh_path, np.asarray(recon.vertices, dtype=np.float64))
    metrics["std_residual_spearman"] = None
    if std is not None and len(std) >= 3:
        from endorecon.evaluation.depth_metrics import std_error_spearman

        rho = std_error_spearman(std, vertex_residual, np.isfinite(std))
        metrics["std_residual_spearman"] = None if not np.isfinite(rho) else rho
    save_residual_heatmap(
        recon_reg, vertex_residual, out_dir / HEATMAP_FILE, vmax_mm=vmax_mm, n_views=heatmap_views,
        title=f"{mesh_path.name}: mean {metrics['mean_mm']:.3f} mm, max {metrics['max_mm']:.3f} mm",
    )
    save_residual_histogram(residual, out_dir / HISTOGRAM_FILE, title=mesh_path.name)
    metrics["seconds"] = time.perf_counter() - t_start
    metrics["inputs"] = inputs
    atomic_write_text(metrics_path, json.dumps(_finite_or_null(metrics), indent=2, allow_nan=False))
    return metrics

"""Accuracy of an SfM result against reference poses / a reference surface (benchmarks and tests).

Both the trajectory and the points are compared after one similarity (Sim(3),
Umeyama on the camera centres of the frames registered in both), since SfM
is defined up to scale and a rigid motion.
"""

from __future__ import annotations

import numpy as np
import torch

from endorecon.geometry import apply_sim3, camera_centers, relative_pose, rotation_angle_deg, umeyama


def trajectory_error(est_cam_from_world: np.ndarray, ref_cam_from_world: np.ndarray) -> dict:
    """Compare estimated poses with reference poses after a Sim(3) fit of the camera centres.

    Args:
        est_cam_from_world, ref_cam_from_world: (N, 4, 4); NaN rows (unregistered) are skipped.
    Returns:
        dict: ``frames`` compared, ``sim3`` (scale, R, t) mapping estimate -> reference,
        ``center_rmse`` (reference units), ``path_length`` (reference), ``center_rmse_rel`` (rmse / path length),
        ``rel_rotation_deg`` (mean angle error of consecutive relative rotations),
        ``rel_translation_rel`` (mean |Δt_est·s − Δt_ref| / mean |Δt_ref| over consecutive frames).
    """
    ok = np.isfinite(est_cam_from_world).all(axis=(1, 2)) & np.isfinite(ref_cam_from_world).all(axis=(1, 2))
    idx = np.nonzero(ok)[0]
    if len(idx) < 3:
        raise ValueError(f"need >= 3 frames registered in both, got {len(idx)}")
    est = torch.from_numpy(est_cam_from_world[idx])
    ref = torch.from_numpy(ref_cam_from_world[idx])
    c_est = camera_centers(est).numpy()
    c_ref = camera_centers(ref).numpy()
    s, R, t = umeyama(c_est, c_ref)
    aligned = apply_sim3(s, R, t, c_est)
    rmse = float(np.sqrt(((aligned - c_ref) ** 2).sum(1).mean()))
    path = float(np.linalg.norm(np.diff(c_ref, axis=0), axis=1).sum())
    # consecutive relative motion (invariant to the world frame; translations scaled by s)
    rel_est = relative_pose(est[:-1], est[1:])
    rel_ref = relative_pose(ref[:-1], ref[1:])
    rot_err = rotation_angle_deg(rel_est[:, :3, :3].transpose(1, 2) @ rel_ref[:, :3, :3]).numpy()
    dt = (s * rel_est[:, :3, 3] - rel_ref[:, :3, 3]).norm(dim=1).numpy()
    step = rel_ref[:, :3, 3].norm(dim=1).numpy()
    return dict(
        frames=int(len(idx)),
        sim3=(s, R, t),
        center_rmse=rmse,
        path_length=path,
        center_rmse_rel=rmse / path if path > 0 else float("nan"),
        rel_rotation_deg=float(rot_err.mean()),
        rel_translation_rel=float(dt.mean() / step.mean()) if step.mean() > 0 else float("nan"),
    )


def point_to_mesh_distance(points: np.ndarray, mesh_path) -> np.ndarray:
    """Unsigned distance of (P, 3) points to a triangle mesh (PLY), in the mesh's units."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    d = scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32)))
    return d.numpy().astype(np.float64)


def aligned_points(points: np.ndarray, sim3) -> np.ndarray:
    s, R, t = sim3
    return apply_sim3(s, R, t, np.asarray(points, dtype=np.float64))

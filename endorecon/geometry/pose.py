"""Rigid poses.

Convention (the one place it is stated): a pose is ``cam_from_world``, a 4x4
matrix T with x_cam = R x_world + t, as COLMAP.  Every transform is named by
its frames: ``b_from_a`` maps coordinates in frame a to frame b, so
``c_from_a = c_from_b @ b_from_a``.  A relative pose between two cameras is
``cam_j_from_cam_i = cam_j_from_world @ inv(cam_i_from_world)``.

Quaternions are (w, x, y, z), unit norm.  Twists ``xi`` are (v, w): translation
part first, rotation (axis-angle) second; :func:`se3_exp` is the true
exponential map of SE(3).
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

from endorecon.geometry._checks import check_shape


def invert_pose(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms.  T: (B, 4, 4) -> (B, 4, 4) (``a_from_b`` -> ``b_from_a``)."""
    check_shape(T, "T", (None, 4, 4))
    R = T[:, :3, :3]
    t = T[:, :3, 3:]
    Rt = R.transpose(1, 2)
    top = torch.cat([Rt, -Rt @ t], dim=2)
    bottom = T.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(T.shape[0], 1, 4)
    return torch.cat([top, bottom], dim=1)


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply ``b_from_a`` to points in frame a.

    Args:
        T: (B, 4, 4).
        points: (B, N, 3).
    Returns:
        (B, N, 3) points in frame b.
    """
    B = check_shape(T, "T", (None, 4, 4))[0]
    check_shape(points, "points", (B, None, 3))
    return points @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]


def relative_pose(cam_a_from_world: torch.Tensor, cam_b_from_world: torch.Tensor) -> torch.Tensor:
    """``cam_b_from_cam_a = cam_b_from_world @ inv(cam_a_from_world)``.  Both (B, 4, 4) -> (B, 4, 4)."""
    check_shape(cam_a_from_world, "cam_a_from_world", (None, 4, 4))
    check_shape(cam_b_from_world, "cam_b_from_world", (cam_a_from_world.shape[0], 4, 4))
    return cam_b_from_world @ invert_pose(cam_a_from_world)


def camera_centers(cam_from_world: torch.Tensor) -> torch.Tensor:
    """Camera centres in world coordinates, c = −Rᵀ t.  (B, 4, 4) -> (B, 3)."""
    check_shape(cam_from_world, "cam_from_world", (None, 4, 4))
    R = cam_from_world[:, :3, :3]
    t = cam_from_world[:, :3, 3:]
    return (-R.transpose(1, 2) @ t)[..., 0]


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (w, x, y, z) to rotation matrices.  q: (B, 4) -> (B, 3, 3).  (Normalises q.)"""
    check_shape(q, "q", (None, 4))
    return quaternion_to_rotation_matrix(q / q.norm(dim=-1, keepdim=True))


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to unit quaternions (w, x, y, z) with w >= 0.  R: (B, 3, 3) -> (B, 4)."""
    check_shape(R, "R", (None, 3, 3))
    q = rotation_matrix_to_quaternion(R.contiguous())
    return torch.where(q[:, :1] < 0, -q, q)


def pose_from_rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Assemble (B, 4, 4) from R (B, 3, 3) and t (B, 3)."""
    B = check_shape(R, "R", (None, 3, 3))[0]
    check_shape(t, "t", (B, 3))
    top = torch.cat([R, t[:, :, None]], dim=2)
    bottom = R.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(B, 1, 4)
    return torch.cat([top, bottom], dim=1)


def _hat(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[:, 0])
    return torch.stack(
        [torch.stack([z, -w[:, 2], w[:, 1]], -1), torch.stack([w[:, 2], z, -w[:, 0]], -1),
         torch.stack([-w[:, 1], w[:, 0], z], -1)],
        dim=1,
    )


def _so3_coeffs(theta2: torch.Tensor):
    """A = sin θ/θ, B = (1−cos θ)/θ², C = (θ − sin θ)/θ³, with Taylor series near 0 (smooth gradients)."""
    small = theta2 < 1e-6
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    th = t2.sqrt()
    A = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(th) / th)
    # 1 − cos θ = 2 sin²(θ/2): no cancellation (in float32 the difference lost ~3 % at θ ~ 1e-3, and se3_log's
    # 1 − A/(2B) then moved translations by up to 12 %)
    Bc = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, 2 * torch.sin(th / 2) ** 2 / t2)
    C = torch.where(small, 1.0 / 6 - theta2 / 120 + theta2**2 / 5040, (th - torch.sin(th)) / (t2 * th))
    return A, Bc, C


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axis-angle (B, 3) -> rotation (B, 3, 3)."""
    check_shape(w, "w", (None, 3))
    W = _hat(w)
    A, Bc, _ = _so3_coeffs((w * w).sum(-1))
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    return eye + A[:, None, None] * W + Bc[:, None, None] * (W @ W)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential map of SE(3).  xi: (B, 6) = (v, w) -> (B, 4, 4)."""
    check_shape(xi, "xi", (None, 6))
    v, w = xi[:, :3], xi[:, 3:]
    W = _hat(w)
    A, Bc, C = _so3_coeffs((w * w).sum(-1))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    WW = W @ W
    R = eye + A[:, None, None] * W + Bc[:, None, None] * WW
    V = eye + Bc[:, None, None] * W + C[:, None, None] * WW
    return pose_from_rt(R, (V @ v[:, :, None])[..., 0])


def _quaternion_angle(q: torch.Tensor) -> torch.Tensor:
    """Rotation angle (rad, [0, π]) of unit quaternions (B, 4) with w >= 0: accurate near 0 and π,
    where ``arccos`` of the trace is not (in float32 every angle under ~0.02 deg reads 0)."""
    return 2 * torch.atan2(q[:, 1:].norm(dim=-1), q[:, 0])


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Logarithm of SO(3): (B, 3, 3) -> axis-angle (B, 3).  Via quaternions (stable near 0 and π)."""
    q = matrix_to_quaternion(R)
    vn = q[:, 1:].norm(dim=-1)
    angle = _quaternion_angle(q)
    small = vn < 1e-8
    scale = torch.where(small, 2.0 / q[:, 0].clamp(min=1e-12), angle / vn.clamp(min=1e-12))
    return q[:, 1:] * scale[:, None]


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Logarithm of SE(3): (B, 4, 4) -> (B, 6) = (v, w), inverse of :func:`se3_exp`."""
    check_shape(T, "T", (None, 4, 4))
    w = so3_log(T[:, :3, :3])
    W = _hat(w)
    theta2 = (w * w).sum(-1)
    A, Bc, _ = _so3_coeffs(theta2)
    small = theta2 < 1e-6
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    # V^-1 = I − W/2 + (1/θ²)(1 − A/(2B)) W²
    D = torch.where(small, 1.0 / 12 + theta2 / 720, (1 - A / (2 * Bc)) / t2)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(W)
    Vinv = eye - 0.5 * W + D[:, None, None] * (W @ W)
    v = (Vinv @ T[:, :3, 3:])[..., 0]
    return torch.cat([v, w], dim=-1)


def rotation_angle_deg(R: torch.Tensor) -> torch.Tensor:
    """Rotation angle of (B, 3, 3) rotations in degrees (B,), in [0, 180] (the angle of :func:`so3_log`)."""
    return torch.rad2deg(_quaternion_angle(matrix_to_quaternion(R)))

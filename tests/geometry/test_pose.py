"""Analytic tests of poses, quaternions and the SE(3) exponential map."""

import math

import torch

from endorecon.geometry import (
    camera_centers,
    invert_pose,
    matrix_to_quaternion,
    pose_from_rt,
    quaternion_to_matrix,
    relative_pose,
    rotation_angle_deg,
    se3_exp,
    se3_log,
    so3_exp,
    transform_points,
)

D = torch.float64


def rz(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=D)


def test_invert_and_transform():
    T = pose_from_rt(rz(0.3)[None], torch.tensor([[1.0, 2.0, 3.0]], dtype=D))
    p = torch.randn(1, 7, 3, dtype=D)
    back = transform_points(invert_pose(T), transform_points(T, p))
    assert torch.allclose(back, p)
    assert torch.allclose(T @ invert_pose(T), torch.eye(4, dtype=D)[None])


def test_camera_center_of_pure_translation():
    # A camera at world position c looking down +z: cam_from_world = [I | -c].
    c = torch.tensor([[1.0, -2.0, 0.5]], dtype=D)
    T = pose_from_rt(torch.eye(3, dtype=D)[None], -c)
    assert torch.allclose(camera_centers(T), c)


def test_relative_pose_pure_translation_and_rotation():
    Ta = pose_from_rt(torch.eye(3, dtype=D)[None], torch.zeros(1, 3, dtype=D))
    Tb = pose_from_rt(torch.eye(3, dtype=D)[None], torch.tensor([[0.0, 0.0, -1.0]], dtype=D))  # b is 1 forward
    b_from_a = relative_pose(Ta, Tb)
    # A point 3 in front of a is 2 in front of b.
    p = transform_points(b_from_a, torch.tensor([[[0.0, 0.0, 3.0]]], dtype=D))
    assert torch.allclose(p, torch.tensor([[[0.0, 0.0, 2.0]]], dtype=D))
    Tc = pose_from_rt(rz(0.5)[None], torch.zeros(1, 3, dtype=D))
    assert torch.allclose(relative_pose(Ta, Tc)[0, :3, :3], rz(0.5))


def test_quaternion_roundtrip_and_known_value():
    # 90 degrees about z: q = (cos 45, 0, 0, sin 45).
    q = torch.tensor([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]], dtype=D)
    assert torch.allclose(quaternion_to_matrix(q)[0], rz(math.pi / 2), atol=1e-12)
    R = so3_exp(torch.randn(5, 3, dtype=D))
    assert torch.allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-10)
    assert (matrix_to_quaternion(R)[:, 0] >= 0).all()


def test_se3_exp_known_and_log_inverse():
    xi = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.7]], dtype=D)
    assert torch.allclose(se3_exp(xi)[0, :3, :3], rz(0.7))
    # Pure translation.
    xi = torch.tensor([[1.0, 2.0, 3.0, 0.0, 0.0, 0.0]], dtype=D)
    assert torch.allclose(se3_exp(xi)[0, :3, 3], xi[0, :3])
    xi = torch.randn(6, 6, dtype=D) * 0.5
    assert torch.allclose(se3_log(se3_exp(xi)), xi, atol=1e-9)
    # Screw motion: rotating by theta about z while translating v along z gives t = (0, 0, v).
    xi = torch.tensor([[0.0, 0.0, 2.0, 0.0, 0.0, 1.0]], dtype=D)
    assert torch.allclose(se3_exp(xi)[0, :3, 3], torch.tensor([0.0, 0.0, 2.0], dtype=D))
    assert torch.allclose(rotation_angle_deg(se3_exp(xi)[:, :3, :3]), torch.tensor([math.degrees(1.0)], dtype=D))


def test_se3_exp_small_angle_is_smooth():
    xi = torch.tensor([[0.1, 0.2, 0.3, 1e-9, 0.0, 0.0]], dtype=D)
    T = se3_exp(xi)
    assert torch.isfinite(T).all()
    assert torch.allclose(T[0, :3, 3], xi[0, :3], atol=1e-8)


def test_gradchecks():
    xi = (torch.randn(3, 6, dtype=D) * 0.3).requires_grad_()
    assert torch.autograd.gradcheck(se3_exp, (xi,))
    xi0 = torch.zeros(2, 6, dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(se3_exp, (xi0,))
    T = se3_exp(torch.randn(2, 6, dtype=D) * 0.3).detach().requires_grad_()
    assert torch.autograd.gradcheck(invert_pose, (T,))
    p = torch.randn(2, 4, 3, dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(transform_points, (T, p))
    q = torch.randn(3, 4, dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(quaternion_to_matrix, (q,))


def test_rotation_angle_deg_small_and_large_angles():
    # Angles about random axes, from 1e-4 deg (float32 arccos of the trace reads 0 there) to 180 deg.
    angles = torch.tensor([1e-4, 5e-3, 0.3, 45.0, 120.0, 179.0, 180.0], dtype=D)
    axes = torch.nn.functional.normalize(torch.randn(len(angles), 3, dtype=D, generator=torch.Generator().manual_seed(0)), dim=-1)
    xi = torch.cat([torch.zeros(len(angles), 3, dtype=D), axes * torch.deg2rad(angles)[:, None]], -1)
    R = se3_exp(xi)[:, :3, :3]
    assert torch.allclose(rotation_angle_deg(R), angles, rtol=1e-9, atol=1e-9)
    got32 = rotation_angle_deg(R.float())
    assert torch.allclose(got32[:3].double(), angles[:3], rtol=1e-3)
    assert torch.allclose(got32.double(), angles, atol=1e-3)
    assert rotation_angle_deg(torch.eye(3, dtype=D)[None]).item() == 0.0


def test_se3_log_in_float32_at_small_rotations():
    """Just above the Taylor cut-off (0.06-0.3 deg) float32 lost the translation by up to 12 %: 1 − cos θ
    cancelled in B = (1 − cos θ)/θ², and se3_log's 1 − A/(2B) amplified it."""
    g = torch.Generator().manual_seed(0)
    for angle in (0.9e-3, 1.2e-3, 2e-3, 5e-3, 0.05, 1.0):
        axis = torch.randn(8, 3, generator=g, dtype=torch.float64)
        w = angle * axis / axis.norm(dim=1, keepdim=True)
        v = 2.5 * torch.randn(8, 3, generator=g, dtype=torch.float64)
        xi = torch.cat([v, w], 1)
        back = se3_log(se3_exp(xi).float()).double()
        assert (back[:, :3] - v).norm(dim=1).max() < 1e-5 * v.norm(dim=1).max(), angle
        A = se3_exp(xi.float()).double()
        assert (A - se3_exp(xi)).abs().max() < 1e-5, angle

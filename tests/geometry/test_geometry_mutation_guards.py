"""Tests that mutations of endorecon/geometry survived before (a review ran single-point mutations): each fails under its mutation."""

import torch

from endorecon.geometry import pose_from_rt, relative_pose, so3_exp, transform_points

D = torch.float64


def test_relative_pose_of_general_poses_composes_to_b():
    """cam_b_from_cam_a @ cam_a_from_world == cam_b_from_world, for poses that are neither identity nor
    commuting (the existing check has cam_a = identity, where inv(a) @ b == b @ inv(a))."""
    g = torch.Generator().manual_seed(0)
    Ta = pose_from_rt(so3_exp(torch.randn(3, 3, generator=g, dtype=D)), torch.randn(3, 3, generator=g, dtype=D))
    Tb = pose_from_rt(so3_exp(torch.randn(3, 3, generator=g, dtype=D)), torch.randn(3, 3, generator=g, dtype=D))
    b_from_a = relative_pose(Ta, Tb)
    torch.testing.assert_close(b_from_a @ Ta, Tb)
    X_world = torch.randn(3, 5, 3, generator=g, dtype=D)
    torch.testing.assert_close(transform_points(b_from_a, transform_points(Ta, X_world)),
                               transform_points(Tb, X_world))


def test_large_rotations_keep_w_non_negative_and_their_angle():
    """kornia returns w < 0 for many rotations beyond 120 deg: without the w >= 0 flip the angle read
    2·atan2(|v|, w) exceeds 180 deg (rotation errors of 199.6 instead of 160.4 deg) and so3_log is wrong."""
    import math

    from endorecon.geometry import matrix_to_quaternion, rotation_angle_deg, so3_log

    g = torch.Generator().manual_seed(0)
    w = torch.randn(20, 3, generator=g, dtype=D)
    w = w / w.norm(dim=1, keepdim=True) * 2.8
    R = so3_exp(w)
    assert (matrix_to_quaternion(R)[:, 0] >= 0).all()
    torch.testing.assert_close(rotation_angle_deg(R), torch.full((20,), math.degrees(2.8), dtype=D))
    torch.testing.assert_close(so3_log(R), w)


def test_so3_log_below_the_small_angle_switch_is_the_inverse_of_exp():
    """Angles under ~2e-8 rad take so3_log's 2/w branch (the log at, and gradient near, the identity)."""
    from endorecon.geometry import so3_log

    w = torch.tensor([[3e-9, -1e-9, 2e-9]], dtype=D)
    torch.testing.assert_close(so3_log(so3_exp(w)), w, rtol=1e-6, atol=0)


def test_camera_centers_of_a_rotated_camera():
    """c = -Rᵀt: the camera maps its own centre to the origin (the existing check has R = I)."""
    from endorecon.geometry import camera_centers, invert_pose

    g = torch.Generator().manual_seed(1)
    T = pose_from_rt(so3_exp(torch.randn(4, 3, generator=g, dtype=D)), torch.randn(4, 3, generator=g, dtype=D))
    c = camera_centers(T)
    torch.testing.assert_close(transform_points(T, c[:, None]), torch.zeros(4, 1, 3, dtype=D))
    torch.testing.assert_close(c, invert_pose(T)[:, :3, 3])


def test_umeyama_returns_a_rotation_for_mirrored_points():
    """dst a mirror image of src: the best orthogonal map is a reflection; Umeyama's D fix must still give
    det R = +1 (a reflected 'rotation' flips the reconstruction's handedness)."""
    from endorecon.geometry import umeyama

    g = torch.Generator().manual_seed(2)
    src = torch.randn(30, 3, generator=g, dtype=D)
    dst = src * torch.tensor([1.0, 1.0, -1.0], dtype=D)
    _, R, _ = umeyama(src, dst)
    assert torch.det(R).item() > 0.999
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=D))


def test_sample_bilinear_inside_is_the_pixel_centre_hull():
    """inside is documented as uv in [0, W-1] x [0, H-1] (± 1e-4): half a pixel beyond the last centre the
    sample is half zero padding and must not read as inside."""
    from endorecon.geometry import sample_bilinear

    img = torch.ones(1, 1, 4, 5, dtype=D)
    uv = torch.tensor([[[[4.0, 1.0], [4.5, 1.0], [1.0, 3.0], [1.0, 3.5], [-0.5, 1.0]]]], dtype=D)
    vals, inside = sample_bilinear(img, uv)
    assert inside[0, 0, 0].tolist() == [True, False, True, False, False]
    torch.testing.assert_close(vals[0, 0, 0, [0, 2]], torch.ones(2, dtype=D))


def test_mask_bbox_crop_window_stays_inside_the_image_at_the_border():
    """A mask blob smaller than one block in the bottom-right corner: the centred window would stick out."""
    from endorecon.geometry import mask_bbox_crop

    mask = torch.zeros(200, 300, dtype=torch.bool)
    mask[190:, 290:] = True
    x0, y0, w, h = mask_bbox_crop(mask, 64)
    assert (w, h) == (64, 64)
    assert (x0, y0) == (300 - 64, 200 - 64)


def test_warped_std_carries_the_jacobian_of_the_warp():
    """std_j_in_i = |∂z_i/∂d_j|·std_j; with a rotation ∂z_i/∂d_j != 1 (pure translation, the only case
    checked elsewhere, has it 1).  Checked against a finite difference of a uniform shift of depth_j."""
    from endorecon.geometry import warp_depth

    K = torch.tensor([[[20.0, 0.0, 7.5], [0.0, 20.0, 5.5], [0.0, 0.0, 1.0]]], dtype=D)
    R = so3_exp(torch.tensor([[0.0, 0.25, 0.05]], dtype=D))
    T = pose_from_rt(R, torch.tensor([[0.3, 0.0, 0.2]], dtype=D))
    d = torch.full((1, 1, 12, 16), 4.0, dtype=D)
    s = torch.full_like(d, 0.2)
    out, valid, std = warp_depth(d, d, K, T, std_j=s)
    h = 1e-6
    fd = (warp_depth(d + h, d, K, T)[0] - warp_depth(d - h, d, K, T)[0]) / (2 * h)
    assert valid.sum() > 20
    a = fd[valid]
    assert (a - 1).abs().max() > 0.01  # the case does test the Jacobian
    torch.testing.assert_close(std[valid], a.abs() * 0.2, rtol=1e-6, atol=1e-9)

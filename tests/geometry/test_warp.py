"""Analytic tests of flow, sampling and depth warping."""

import torch

from endorecon.geometry import flow_from_depth, pose_from_rt, sample_bilinear, so3_exp, warp_depth

D = torch.float64
H, W = 12, 16


def K_():
    return torch.tensor([[[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]], dtype=D)


def translation(t):
    return pose_from_rt(torch.eye(3, dtype=D)[None], torch.tensor([t], dtype=D))


def test_pure_translation_fronto_parallel_plane_flow():
    # Camera j is camera i moved by +0.1 along x (in i's frame): cam_j_from_cam_i has t = (-0.1, 0, 0).
    # A plane at depth 2: every pixel moves by -fx * 0.1 / 2 = -1 pixel in u.
    depth = torch.full((1, 1, H, W), 2.0, dtype=D)
    flow, z_j = flow_from_depth(depth, K_(), translation([-0.1, 0.0, 0.0]))
    assert torch.allclose(flow[:, 0], torch.full((1, H, W), -1.0, dtype=D))
    assert torch.allclose(flow[:, 1], torch.zeros(1, H, W, dtype=D))
    assert torch.allclose(z_j, depth)


def test_pure_rotation_flow_is_depth_independent():
    T = pose_from_rt(so3_exp(torch.tensor([[0.0, 0.02, 0.0]], dtype=D)), torch.zeros(1, 3, dtype=D))
    f1, _ = flow_from_depth(torch.full((1, 1, H, W), 1.0, dtype=D), K_(), T)
    f2, _ = flow_from_depth(torch.rand(1, 1, H, W, dtype=D) * 5 + 1, K_(), T)
    assert torch.allclose(f1, f2)


def test_sample_bilinear_pixel_centres():
    img = torch.arange(H * W, dtype=D).view(1, 1, H, W)
    uv = torch.tensor([[[[3.0, 2.0], [3.5, 2.0], [-1.0, 0.0]]]], dtype=D)
    vals, inside = sample_bilinear(img, uv)
    assert vals[0, 0, 0, 0] == 2 * W + 3
    assert vals[0, 0, 0, 1] == 2 * W + 3.5
    assert inside[0, 0, 0].tolist() == [True, True, False]


def test_warp_depth_consistent_plane_forward_motion():
    # Camera j 0.5 ahead of i along the optical axis; plane at z = 3 in i, so z = 2.5 in j.
    depth_i = torch.full((1, 1, H, W), 3.0, dtype=D)
    depth_j = torch.full((1, 1, H, W), 2.5, dtype=D)
    std_j = torch.full((1, 1, H, W), 0.1, dtype=D)
    warped, valid, std_w = warp_depth(depth_j, depth_i, K_(), translation([0.0, 0.0, -0.5]), std_j=std_j)
    assert valid.any()
    assert torch.allclose(warped[valid], depth_i[valid])
    assert torch.allclose(std_w[valid], torch.full_like(std_w[valid], 0.1))
    # Zooming in: i's border pixels leave j's image.
    assert not valid[0, 0, 0, 0]


def test_warp_depth_detects_offset():
    # If j's depth is 0.2 too large (surface further away), the warped depth is 0.2 larger too (pure z motion).
    depth_i = torch.full((1, 1, H, W), 3.0, dtype=D)
    depth_j = torch.full((1, 1, H, W), 2.7, dtype=D)
    warped, valid, _ = warp_depth(depth_j, depth_i, K_(), translation([0.0, 0.0, -0.5]))
    assert torch.allclose(warped[valid], torch.full_like(warped[valid], 3.2))


def test_warp_depth_refuses_a_sample_that_blends_in_a_pixel_without_depth():
    # j's depth is 0 (a hole, or outside its mask) from column 8 on; i's pixels land half-way between j's
    # columns, so the sample next to the hole would read half the true depth.
    depth_i = torch.full((1, 1, H, W), 2.0, dtype=D)
    depth_j = depth_i.clone()
    depth_j[..., 8:] = 0.0
    T = translation([0.05, 0.0, 0.0])  # flow = 20 * 0.05 / 2 = +0.5 px
    warped, valid, std_w = warp_depth(depth_j, depth_i, K_(), T, std_j=torch.full_like(depth_j, 0.1))
    # pixel u of i lands at u + 0.5 in j: columns 0-6 sample only j's columns 0-7.
    assert valid[0, 0, :, :7].all() and not valid[0, 0, :, 7:].any()
    assert torch.allclose(warped[valid], depth_i[valid])
    assert torch.allclose(std_w[valid], torch.full_like(std_w[valid], 0.1))



def test_warp_depth_non_finite_depths_are_invalid_not_inf():
    # an overflowed prediction (inf) or NaN in j, or inf in i: never a valid warped depth, and no NaN elsewhere
    depth_i = torch.full((1, 1, H, W), 2.0, dtype=D)
    depth_j = depth_i.clone()
    depth_j[..., 3, 3] = float("inf")
    depth_j[..., 6, 9] = float("nan")
    depth_i[..., 10, 2] = float("inf")
    warped, valid, std_w = warp_depth(depth_j, depth_i, K_(), translation([0.0, 0.0, 0.0]),
                                      std_j=torch.full_like(depth_j, 0.1))
    assert not valid[0, 0, 3, 3] and not valid[0, 0, 6, 9] and not valid[0, 0, 10, 2]
    assert torch.isfinite(warped).all() and torch.isfinite(std_w).all()
    assert valid.sum() == H * W - 3 and torch.allclose(warped[valid], depth_i[valid])

def test_warp_gradcheck():
    depth_i = (torch.rand(1, 1, 4, 5, dtype=D) * 0.1 + 3.0).requires_grad_()
    depth_j = (torch.rand(1, 1, 4, 5, dtype=D) * 0.1 + 3.0).requires_grad_()
    K = torch.tensor([[[4.0, 0, 2.0], [0, 4.0, 1.5], [0, 0, 1]]], dtype=D)
    T = translation([0.01, 0.0, 0.0])

    def f(dj, di):
        return warp_depth(dj, di, K, T)[0]

    assert torch.autograd.gradcheck(f, (depth_j, depth_i))
    assert torch.autograd.gradcheck(lambda d: flow_from_depth(d, K, T)[0], (depth_i,))

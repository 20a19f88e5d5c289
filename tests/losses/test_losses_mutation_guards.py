"""Tests that mutations of endorecon/losses survived before (a review ran single-point mutations): each fails under its mutation."""

import math

import torch

from endorecon.losses import carried_std, depth_consistency_loss, sparse_flow_loss

from test_nll import H, W, _K, _pose


def test_carried_std_falls_back_to_std_i_where_the_warp_misses_j():
    """Pixels of mask_i that leave j's image carry std_i (defined for the loss at any other pose), 0 outside
    mask_i; pixels that land in j carry std_j (pure translation: d z_i / d d_j = 1)."""
    depth = torch.full((1, 1, H, W), 4.0, dtype=torch.float64)
    std_i = torch.full_like(depth, 0.3)
    std_j = torch.full_like(depth, 0.7)
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    mask[..., 0, :] = False
    T = _pose(tx=-1.0)  # 14 * 1 / 4 = 3.5 px left: the 4 left columns miss j
    c = carried_std(depth, std_i, depth, std_j, _K(), T, mask)
    assert (c[..., 0, :] == 0).all()
    torch.testing.assert_close(c[..., 1:, :4], torch.full_like(c[..., 1:, :4], 0.3))
    torch.testing.assert_close(c[..., 1:, 4:], torch.full_like(c[..., 1:, 4:], 0.7))


def test_no_gradient_flows_into_std_pose():
    """std_pose is documented as detached: PGO may pass a pose tensor that takes part in the graph."""
    g = torch.Generator().manual_seed(11)
    d_i = torch.rand(1, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4
    d_j = torch.rand(1, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4
    s = torch.rand(1, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 0.1
    K, T = _K(), _pose(tx=0.3, angle=0.05)
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    flow = torch.randn(1, 2, H, W, generator=g, dtype=torch.float64)
    for fn in (lambda t0: depth_consistency_loss(d_i, s, d_j, s, K, T, mask, std_pose=t0),
               lambda t0: sparse_flow_loss(d_i, s, K, T, flow, mask, std_pose=t0)):
        T0 = _pose(tx=0.25, angle=0.04).requires_grad_()
        loss = fn(T0)
        assert math.isfinite(loss.item())
        assert not loss.requires_grad or torch.autograd.grad(loss, T0, allow_unused=True)[0] is None

"""Analytic values, gradchecks, masking and NaN isolation of the four NLL losses."""

import math

import pytest
import torch

from endorecon.geometry import flow_from_depth
from endorecon.losses import (
    carried_std,
    dense_simulation_loss,
    depth_consistency_loss,
    flow_depth_derivative,
    gaussian_nll,
    propagated_flow_std,
    sparse_depth_loss,
    sparse_flow_loss,
    sparse_flow_loss_points,
)

H, W = 12, 16


def _K(B=1, dtype=torch.float64):
    K = torch.tensor([[14.0, 0.0, 7.5], [0.0, 13.0, 5.5], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.expand(B, 3, 3).clone()


def _pose(tx=0.0, ty=0.0, tz=0.0, angle=0.0, B=1, dtype=torch.float64):
    T = torch.eye(4, dtype=dtype).repeat(B, 1, 1)
    c, s = math.cos(angle), math.sin(angle)
    T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, s, -s, c
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = tx, ty, tz
    return T


def _rand_mask(B=2, p=0.5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, 1, H, W, generator=g) < p


def test_gaussian_nll_formula():
    x, mu, var = torch.tensor([2.0]), torch.tensor([1.0]), torch.tensor([4.0])
    assert gaussian_nll(x, mu, var, eps=0.0).item() == pytest.approx(0.5 * math.log(4.0) + 1.0 / 8.0)


# ---------------------------------------------------------------- sparse depth / dense simulation
@pytest.mark.parametrize("loss_fn", [sparse_depth_loss, dense_simulation_loss])
def test_pixel_losses_analytic(loss_fn):
    B = 2
    depth = torch.full((B, 1, H, W), 3.0, dtype=torch.float64)
    std = torch.full_like(depth, 0.5)
    valid = _rand_mask(B)
    same = loss_fn(depth, std, depth.clone(), valid, eps=1e-8)
    assert same.item() == pytest.approx(0.5 * math.log(0.25 + 1e-8), rel=1e-12)
    off = loss_fn(depth, std, depth + 0.2, valid, eps=1e-8, reduction="none")
    want = 0.5 * math.log(0.25 + 1e-8) + 0.04 / (2 * (0.25 + 1e-8))
    assert off.shape == (B,)
    torch.testing.assert_close(off, torch.full((B,), want, dtype=torch.float64))


def test_pixel_loss_reductions_and_empty():
    depth = torch.ones(2, 1, H, W, dtype=torch.float64)
    obs = depth.clone()
    obs[1] = 2.0
    valid = torch.zeros(2, 1, H, W, dtype=torch.bool)
    valid[0, 0, :2] = True  # 32 pixels in sample 0
    valid[1, 0, 0, :4] = True  # 4 pixels in sample 1
    per = sparse_depth_loss(depth, torch.ones_like(depth), obs, valid, reduction="none")
    torch.testing.assert_close(per, torch.tensor([0.0, 0.5], dtype=torch.float64), atol=1e-7, rtol=0)
    mean = sparse_depth_loss(depth, torch.ones_like(depth), obs, valid)
    assert mean.item() == pytest.approx(4 * 0.5 / 36, abs=1e-7)
    none = torch.zeros_like(valid)
    assert dense_simulation_loss(depth, depth, obs, none).item() == 0.0
    assert dense_simulation_loss(depth, depth, obs, none, reduction="none").tolist() == [0.0, 0.0]


@pytest.mark.parametrize("loss_fn", [sparse_depth_loss, dense_simulation_loss])
def test_pixel_losses_mask_and_nan(loss_fn):
    g = torch.Generator().manual_seed(1)
    depth = (torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) + 1).requires_grad_()
    std = (torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) + 0.1).requires_grad_()
    obs = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) + 1
    valid = _rand_mask()
    base = loss_fn(depth, std, obs, valid)
    wild = torch.where(valid, obs, torch.full_like(obs, 1e6))
    assert loss_fn(depth, std, wild, valid).item() == pytest.approx(base.item(), rel=1e-12)
    nan_obs = torch.where(valid, obs, torch.full_like(obs, float("nan")))
    d_nan = torch.where(valid, depth, torch.full_like(obs, float("nan")))
    s_nan = torch.where(valid, std, torch.full_like(obs, float("inf")))
    out = loss_fn(d_nan, s_nan, nan_obs, valid)
    assert out.item() == pytest.approx(base.item(), rel=1e-12)
    out.backward()
    assert torch.isfinite(depth.grad).all() and torch.isfinite(std.grad).all()
    assert (depth.grad[~valid] == 0).all()


@pytest.mark.parametrize("loss_fn", [sparse_depth_loss, dense_simulation_loss])
def test_pixel_losses_gradcheck(loss_fn):
    g = torch.Generator().manual_seed(2)
    depth = (torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64) + 1).requires_grad_()
    std = (torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64) + 0.2).requires_grad_()
    obs = (torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64) + 1).requires_grad_()
    valid = torch.rand(1, 1, 4, 5, generator=g) < 0.6
    for red in ("mean", "none"):
        assert torch.autograd.gradcheck(lambda d, s, o: loss_fn(d, s, o, valid, reduction=red), (depth, std, obs))


def test_bad_inputs():
    d = torch.ones(1, 1, H, W)
    with pytest.raises(ValueError, match="std"):
        sparse_depth_loss(d, torch.ones(1, 1, H, W + 1), d, d > 0)
    with pytest.raises(ValueError, match="reduction"):
        sparse_depth_loss(d, d, d, d > 0, reduction="sum")
    with pytest.raises(ValueError, match="sparse_flow_ij"):
        sparse_flow_loss(d, d, _K(dtype=torch.float32), _pose(dtype=torch.float32), d, d > 0)


# ---------------------------------------------------------------- depth consistency
def test_depth_consistency_identical_plane():
    """A fronto-parallel plane at z=4 seen by a laterally moved camera: warped depth equals depth_i."""
    B = 1
    depth = torch.full((B, 1, H, W), 4.0, dtype=torch.float64)
    std = torch.full_like(depth, 0.3)
    T = _pose(tx=0.5)
    mask = torch.ones(B, 1, H, W, dtype=torch.bool)
    per = depth_consistency_loss(depth, std, depth, std, _K(), T, mask, reduction="none")
    # std_j carried linearly with d z_i / d d_j = 1 on a pure translation: σ² = 2·0.09.
    assert per.item() == pytest.approx(0.5 * math.log(0.18 + 1e-8), rel=1e-9)
    # Offset of j's plane by 0.1: every valid pixel sees it (x − μ = 0.1).
    per_off = depth_consistency_loss(depth, std, depth + 0.1, std, _K(), T, mask, reduction="none")
    want = 0.5 * math.log(0.18 + 1e-8) + 0.01 / (2 * (0.18 + 1e-8))
    assert per_off.item() == pytest.approx(want, rel=1e-9)


def test_depth_consistency_mask_and_nan():
    g = torch.Generator().manual_seed(3)
    d_i = (torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4).requires_grad_()
    d_j = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4
    s = torch.full_like(d_j, 0.2)
    T, K = _pose(tx=0.3, angle=0.05, B=2), _K(2)
    mask = _rand_mask(2, 0.6, seed=4)
    base = depth_consistency_loss(d_i, s, d_j, s, K, T, mask, reduction="none")
    wild = torch.where(mask, d_i, torch.full_like(d_i, float("nan")))
    wild_s = torch.where(mask, s, torch.full_like(s, -1e9))
    out = depth_consistency_loss(wild, wild_s, d_j, s, K, T, mask, reduction="none")
    torch.testing.assert_close(out, base)
    out.sum().backward()
    assert torch.isfinite(d_i.grad).all() and (d_i.grad[~mask] == 0).all()


def test_depth_consistency_leaves_out_js_depth_outside_mask_j():
    """j's depth outside its mask is unconstrained network output: with mask_j it changes nothing."""
    depth = torch.full((1, 1, H, W), 4.0, dtype=torch.float64)
    std = torch.full_like(depth, 0.3)
    T, K = _pose(tx=-0.5), _K()  # i's pixels move 14 * 0.5 / 4 = 1.75 px left in j, onto j's masked columns
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    mask[..., :3] = False
    garbage = depth.clone()
    garbage[..., :3] = 50.0
    clean = depth_consistency_loss(depth, std, depth, std, K, T, mask, reduction="none", mask_j=mask)
    with_garbage = depth_consistency_loss(depth, std, garbage, std, K, T, mask, reduction="none", mask_j=mask)
    assert clean.item() == pytest.approx(0.5 * math.log(0.18 + 1e-8), rel=1e-9)
    torch.testing.assert_close(with_garbage, clean)
    # Without mask_j the garbage is read (the previous behaviour of the training loss).
    assert depth_consistency_loss(depth, std, garbage, std, K, T, mask, reduction="none").item() > 10
    c_clean = carried_std(depth, std, depth, std, K, T, mask, mask)
    std_garbage = std.clone()
    std_garbage[..., :3] = 2.0
    c_garbage = carried_std(depth, std, garbage, std_garbage, K, T, mask, mask)
    torch.testing.assert_close(c_garbage[mask], c_clean[mask])


def test_min_valid_gives_nan_instead_of_zero_for_too_little_overlap():
    d = torch.full((2, 1, H, W), 4.0, dtype=torch.float64)
    s = torch.full_like(d, 0.3)
    T, K = _pose(tx=0.5, B=2), _K(2)
    mask = torch.ones(2, 1, H, W, dtype=torch.bool)
    hole = d.clone()
    hole[1] = 0.0  # the second pair has no depth in j at all: no overlap
    plain = depth_consistency_loss(d, s, hole, s, K, T, mask, reduction="none")
    assert plain[1].item() == 0.0  # the default: 0 for none (pose graph optimisation sums edges)
    checked = depth_consistency_loss(d, s, hole, s, K, T, mask, reduction="none", min_valid=10)
    assert checked[0].item() == pytest.approx(plain[0].item()) and math.isnan(checked[1].item())
    # the count is of the pixels the loss used, not of mask_i: i's pixels that leave j's image are not in it
    overlap = depth_consistency_loss(d, s, d, s, K, T, mask, reduction="none", min_valid=H * W)
    assert torch.isnan(overlap).all()
    sim_valid = torch.zeros_like(mask)
    sim_valid[0, :, :2, :2] = True
    dense = dense_simulation_loss(d, s, d, sim_valid, reduction="none", min_valid=4)
    assert math.isfinite(dense[0].item()) and math.isnan(dense[1].item())
    flow, _ = flow_from_depth(d, K, T)
    fl = sparse_flow_loss(d, s, K, T, flow, sim_valid, reduction="none", min_valid=5)
    assert torch.isnan(fl).all()


def test_propagated_flow_std_is_non_negative():
    d = torch.rand(1, 1, H, W, dtype=torch.float64) * 3 + 1
    sigma = propagated_flow_std(d, 0.1 * d, _K(), _pose(tx=-0.4, tz=0.3, angle=0.1))
    assert (sigma[torch.isfinite(sigma)] >= 0).all() and torch.isfinite(sigma).any()


def test_depth_consistency_gradcheck_including_pose():
    g = torch.Generator().manual_seed(5)
    h, w = 6, 8
    K = torch.tensor([[[7.0, 0.0, 3.5], [0.0, 7.0, 2.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    d_i = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.3 + 4).requires_grad_()
    d_j = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.3 + 4).requires_grad_()
    s_i = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.2 + 0.1).requires_grad_()
    s_j = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.2 + 0.1).requires_grad_()
    T = _pose(tx=0.2, ty=0.1, angle=0.03).requires_grad_()
    mask = torch.ones(1, 1, h, w, dtype=torch.bool)
    fn = lambda a, b, c, d, t: depth_consistency_loss(a, b, c, d, K, t, mask)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (d_i, s_i, d_j, s_j, T))


# ---------------------------------------------------------------- sparse flow
def _flow_case(B=1, tx=0.4, depth_value=4.0, sigma=0.2):
    depth = torch.full((B, 1, H, W), depth_value, dtype=torch.float64)
    std = torch.full_like(depth, sigma)
    K, T = _K(B), _pose(tx=tx, B=B)
    # Pure lateral translation of a fronto-parallel plane: flow_u = fx·tx/z, flow_v = 0 everywhere.
    flow = torch.zeros(B, 2, H, W, dtype=torch.float64)
    flow[:, 0] = 14.0 * tx / depth_value
    valid = _rand_mask(B, 0.3, seed=6)
    return depth, std, K, T, flow, valid


@pytest.mark.parametrize("skew", [0.0, 3.0])  # with skew: its s·∂y/∂d term in ∂u/∂d
def test_flow_depth_derivative_matches_finite_differences(skew):
    g = torch.Generator().manual_seed(7)
    d = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) + 3
    K, T = _K(2), _pose(tx=0.3, ty=-0.2, tz=0.1, angle=0.1, B=2)
    K[:, 0, 1] = skew
    _, z_j = flow_from_depth(d, K, T)
    jac = flow_depth_derivative(d, K, T, z_j)
    h = 1e-6
    fd = (flow_from_depth(d + h, K, T)[0] - flow_from_depth(d - h, K, T)[0]) / (2 * h)
    torch.testing.assert_close(jac, fd, rtol=1e-6, atol=1e-8)


def test_sparse_flow_analytic():
    depth, std, K, T, flow, valid = _flow_case()
    floor = 1e-3
    # ∂u/∂d = −fx·tx/d²; normalised by W.  v has only the floor.
    var_u = (14.0 * 0.4 / 16.0 * 0.2 / 16.0) ** 2 + floor**2
    var_v = floor**2
    want = 0.5 * math.log(var_u + 1e-8) + 0.5 * math.log(var_v + 1e-8)
    got = sparse_flow_loss(depth, std, K, T, flow, valid, flow_std_floor=floor)
    assert got.item() == pytest.approx(want, rel=1e-9)
    off = flow.clone()
    off[:, 1] += 0.8  # 0.8 px in v = 0.8/H normalised
    got_off = sparse_flow_loss(depth, std, K, T, off, valid, flow_std_floor=floor, reduction="none")
    want_off = want + (0.8 / H) ** 2 / (2 * (var_v + 1e-8))
    assert got_off.item() == pytest.approx(want_off, rel=1e-9)


def test_sparse_flow_mask_and_nan():
    g = torch.Generator().manual_seed(8)
    depth = (torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) + 3).requires_grad_()
    std = torch.full_like(depth, 0.2)
    K, T = _K(2), _pose(tx=0.3, angle=0.05, B=2)
    flow = torch.randn(2, 2, H, W, generator=g, dtype=torch.float64)
    valid = _rand_mask(2, 0.3, seed=9)
    base = sparse_flow_loss(depth, std, K, T, flow, valid, reduction="none")
    nan = torch.where(valid, depth, torch.full_like(depth, float("nan")))
    flow_nan = torch.where(valid, flow, torch.full_like(flow, float("inf")))
    out = sparse_flow_loss(nan, std, K, T, flow_nan, valid, reduction="none")
    torch.testing.assert_close(out, base)
    wild = torch.where(valid, flow, flow * 1e5)
    torch.testing.assert_close(sparse_flow_loss(depth, std, K, T, wild, valid, reduction="none"), base)
    out.sum().backward()
    assert torch.isfinite(depth.grad).all() and (depth.grad[~valid] == 0).all()


def test_sparse_flow_ignores_points_behind_camera_j():
    depth, std, K, _, flow, valid = _flow_case()
    T = _pose(tz=-10.0)  # camera j moved 10 units forward: the plane at z=4 is behind it
    out = sparse_flow_loss(depth, std, K, T, flow, valid, reduction="none")
    assert out.item() == 0.0


def test_sparse_flow_gradcheck_including_pose():
    g = torch.Generator().manual_seed(10)
    h, w = 5, 6
    K = torch.tensor([[[6.0, 0.0, 2.5], [0.0, 6.0, 2.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    d = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) + 3).requires_grad_()
    s = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.3 + 0.1).requires_grad_()
    T = _pose(tx=0.3, ty=0.1, tz=0.2, angle=0.05).requires_grad_()
    flow = torch.randn(1, 2, h, w, generator=g, dtype=torch.float64)
    valid = torch.rand(1, 1, h, w, generator=g) < 0.7
    fn = lambda a, b, t: sparse_flow_loss(a, b, K, t, flow, valid, flow_std_floor=1e-2, reduction="none")  # noqa: E731
    assert torch.autograd.gradcheck(fn, (d, s, T))


# ---------------------------------------------------------------- std carried at a fixed pose (PGO)
def _twist_pose(T, xi):
    from endorecon.geometry import se3_exp

    return se3_exp(xi) @ T


def test_std_pose_equal_to_the_pose_changes_nothing():
    g = torch.Generator().manual_seed(11)
    d_i = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4
    d_j = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4
    s = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 0.1
    T, K = _pose(tx=0.3, angle=0.05, B=2), _K(2)
    mask = _rand_mask(2, 0.8, seed=12)
    flow = torch.randn(2, 2, H, W, generator=g, dtype=torch.float64)
    for fn in (lambda **k: depth_consistency_loss(d_i, s, d_j, s, K, T, mask, reduction="none", **k),
               lambda **k: sparse_flow_loss(d_i, s, K, T, flow, mask, reduction="none", **k)):
        torch.testing.assert_close(fn(std_pose=T.clone()), fn(), rtol=1e-12, atol=1e-12)


def test_std_pose_makes_exact_flow_a_stationary_point_of_the_pose():
    """Flow that the depth and pose reproduce exactly: with the std propagated at that fixed pose the NLL's
    gradient w.r.t. the pose is 0; with the std propagated at the free pose, log σ² alone has a gradient
    (∂flow/∂d grows with the baseline), which is what would pull PGO's poses off."""
    depth, std, K, T, flow, valid = _flow_case(tx=0.4)
    xi = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    frozen = sparse_flow_loss(depth, std, K, _twist_pose(T, xi), flow, valid, std_pose=T)
    (g_frozen,) = torch.autograd.grad(frozen, xi)
    free = sparse_flow_loss(depth, std, K, _twist_pose(T, xi), flow, valid)
    (g_free,) = torch.autograd.grad(free, xi)
    assert g_frozen.abs().max() < 1e-9
    assert g_free.abs().max() > 1e-3


def test_std_pose_gradchecks():
    g = torch.Generator().manual_seed(13)
    h, w = 5, 6
    K = torch.tensor([[[6.0, 0.0, 2.5], [0.0, 6.0, 2.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    d = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.3 + 4).requires_grad_()
    d_j = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.3 + 4).requires_grad_()
    s = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) * 0.3 + 0.1).requires_grad_()
    T = _pose(tx=0.3, ty=0.1, tz=0.2, angle=0.05).requires_grad_()
    T0 = _pose(tx=0.25, ty=0.1, tz=0.2, angle=0.04)
    flow = torch.randn(1, 2, h, w, generator=g, dtype=torch.float64)
    valid = torch.rand(1, 1, h, w, generator=g) < 0.7
    mask = torch.ones(1, 1, h, w, dtype=torch.bool)
    flow_fn = lambda a, b, t: sparse_flow_loss(a, b, K, t, flow, valid, flow_std_floor=1e-2, std_pose=T0)  # noqa: E731
    cons_fn = lambda a, b, c, t: depth_consistency_loss(a, b, c, b, K, t, mask, std_pose=T0)  # noqa: E731
    assert torch.autograd.gradcheck(flow_fn, (d, s, T))
    assert torch.autograd.gradcheck(cons_fn, (d, s, d_j, T))


def test_precomputed_stds_equal_std_pose_and_exclude_it():
    """carried_std / propagated_flow_std at a pose, passed in, give exactly the std_pose loss (what PGO caches);
    the flow std is NaN where the point lies behind camera j at that pose, and such points are left out."""
    g = torch.Generator().manual_seed(14)
    d_i = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4
    d_j = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 4
    s = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 0.1
    T, T0, K = _pose(tx=0.3, angle=0.05, B=2), _pose(tx=0.25, angle=0.04, B=2), _K(2)
    mask = _rand_mask(2, 0.8, seed=15)
    flow = torch.randn(2, 2, H, W, generator=g, dtype=torch.float64)
    cons = depth_consistency_loss(d_i, s, d_j, s, K, T, mask, reduction="none", std_pose=T0)
    carried = carried_std(d_i, s, d_j, s, K, T0, mask)
    torch.testing.assert_close(depth_consistency_loss(d_i, s, d_j, s, K, T, mask, reduction="none",
                                                      std_j_in_i=carried), cons, rtol=0, atol=0)
    fl = sparse_flow_loss(d_i, s, K, T, flow, mask, reduction="none", std_pose=T0)
    fstd = propagated_flow_std(d_i, s, K, T0)
    torch.testing.assert_close(sparse_flow_loss(d_i, s, K, T, flow, mask, reduction="none", flow_std_ij=fstd),
                               fl, rtol=0, atol=0)
    # analytic case: no rotation, translation along x only: ∂u/∂d = -fx·tx/d², ∂v/∂d = 0
    T1 = _pose(tx=0.3, B=2)
    fx = float(K[0, 0, 0])
    want_u = fx * 0.3 / d_i**2 * s / W
    torch.testing.assert_close(propagated_flow_std(d_i, s, K, T1)[:, :1].abs(), want_u)
    assert (propagated_flow_std(d_i, s, K, T1)[:, 1:] == 0).all()
    behind = _pose(tz=-10.0, B=2)  # every point behind camera j
    assert torch.isnan(propagated_flow_std(d_i, s, K, behind)).all()
    assert (sparse_flow_loss(d_i, s, K, T, flow, mask, reduction="none",
                             flow_std_ij=propagated_flow_std(d_i, s, K, behind)) == 0).all()
    with pytest.raises(ValueError, match="not both"):
        sparse_flow_loss(d_i, s, K, T, flow, mask, std_pose=T0, flow_std_ij=fstd)
    with pytest.raises(ValueError, match="not both"):
        depth_consistency_loss(d_i, s, d_j, s, K, T, mask, std_pose=T0, std_j_in_i=carried)


# ---------------------------------------------------------------- sparse flow at the points only (PGO)
def _gather_points(depth, K, flow, fstd, valid):
    """Dense maps -> the padded (B, M, .) point tensors of sparse_flow_loss_points (padding NaN, invalid)."""
    from endorecon.geometry import pixel_grid, unproject

    B = depth.shape[0]
    X = unproject(depth, K).flatten(2).transpose(1, 2)
    uv = pixel_grid(H, W, dtype=depth.dtype).reshape(-1, 2)
    idx = [torch.nonzero(valid[b, 0].flatten()).flatten() for b in range(B)]
    M = max(len(i) for i in idx) + 3  # some padding on every sample
    out = [torch.full((B, M, c), float("nan"), dtype=depth.dtype) for c in (3, 2, 2, 2)]
    ok = torch.zeros(B, M, dtype=torch.bool)
    for b, i in enumerate(idx):
        for o, v in zip(out, (X[b, i], uv[i], flow[b].flatten(1)[:, i].T, fstd[b].flatten(1)[:, i].T)):
            o[b, : len(i)] = v
        ok[b, : len(i)] = True
    return (*out, ok)


def test_flow_at_points_equals_the_dense_loss():
    g = torch.Generator().manual_seed(21)
    d = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.5 + 3
    s = torch.rand(2, 1, H, W, generator=g, dtype=torch.float64) * 0.2 + 0.05
    K, T0 = _K(2), _pose(tx=0.3, ty=-0.1, angle=0.05, B=2)
    T = _pose(tx=0.28, ty=-0.08, tz=0.02, angle=0.06, B=2)
    flow = torch.randn(2, 2, H, W, generator=g, dtype=torch.float64) * 2
    valid = torch.stack([_rand_mask(1, 0.2, seed=22)[0], _rand_mask(1, 0.5, seed=23)[0]])
    fstd = propagated_flow_std(d, s, K, T0)
    X, uv, f, fs, ok = _gather_points(d, K, flow, fstd, valid)
    for red in ("none", "mean"):
        want = sparse_flow_loss(d, s, K, T, flow, valid, reduction=red, flow_std_ij=fstd)
        got = sparse_flow_loss_points(X, uv, K, T, f, fs, ok, (H, W), reduction=red)
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    # points behind camera j at the current pose are left out, as in the dense loss
    behind = _pose(tz=-3.4, B=2)
    torch.testing.assert_close(sparse_flow_loss_points(X, uv, K, behind, f, fs, ok, (H, W), reduction="none"),
                               sparse_flow_loss(d, s, K, behind, flow, valid, reduction="none", flow_std_ij=fstd),
                               rtol=1e-12, atol=1e-12)


def test_flow_at_points_analytic_padding_and_nan():
    depth, std, K, T, flow, valid = _flow_case()
    floor = 1e-3
    fstd = propagated_flow_std(depth, std, K, T)
    X, uv, f, fs, ok = _gather_points(depth, K, flow, fstd, valid)
    var_u = (14.0 * 0.4 / 16.0 * 0.2 / 16.0) ** 2 + floor**2
    want = 0.5 * math.log(var_u + 1e-8) + 0.5 * math.log(floor**2 + 1e-8)
    assert sparse_flow_loss_points(X, uv, K, T, f, fs, ok, (H, W)).item() == pytest.approx(want, rel=1e-9)
    # invalid points hold anything (here: wild and inf values) and count neither in value nor gradient
    Xw = torch.where(ok[..., None], X, torch.full_like(X, float("inf"))).requires_grad_()
    fw = torch.where(ok[..., None], f, f.nan_to_num(0) * 1e5)
    out = sparse_flow_loss_points(Xw, uv, K, T, fw, fs, ok, (H, W), reduction="none")
    assert out.item() == pytest.approx(want, rel=1e-9)
    out.sum().backward()
    assert torch.isfinite(Xw.grad).all() and (Xw.grad[~ok] == 0).all()
    assert sparse_flow_loss_points(X, uv, K, T, f, fs, torch.zeros_like(ok), (H, W)).item() == 0.0


def test_flow_at_points_gradcheck():
    g = torch.Generator().manual_seed(24)
    K = _K(1)
    X = torch.rand(1, 7, 3, generator=g, dtype=torch.float64)
    X[..., 2] += 3
    X.requires_grad_()
    uv = torch.rand(1, 7, 2, generator=g, dtype=torch.float64) * 10
    flow = torch.randn(1, 7, 2, generator=g, dtype=torch.float64)
    fs = (torch.rand(1, 7, 2, generator=g, dtype=torch.float64) * 0.05 + 0.01).requires_grad_()
    ok = torch.tensor([[True] * 6 + [False]])
    T = _pose(tx=0.3, ty=0.1, tz=0.2, angle=0.05).requires_grad_()
    fn = lambda a, t, c: sparse_flow_loss_points(a, uv, K, t, flow, c, ok, (H, W), flow_std_floor=1e-2)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (X, T, fs))


def test_gaussian_nll_and_flow_derivative_refuse_shapes_that_would_broadcast():
    from endorecon.losses.nll import flow_depth_derivative, gaussian_nll

    x = torch.zeros(2, 1, 4, 5)
    with pytest.raises(ValueError, match="one shape"):
        gaussian_nll(x, torch.zeros(2, 1, 1, 1), torch.ones_like(x))
    assert gaussian_nll(x, x, torch.ones_like(x)).shape == x.shape
    K = torch.eye(3).expand(2, 3, 3)
    T = torch.eye(4).expand(2, 4, 4)
    with pytest.raises(ValueError, match="z_j"):
        flow_depth_derivative(x, K, T, torch.ones(2, 1, 4, 1))
    with pytest.raises(ValueError, match="cam_j_from_cam_i"):
        flow_depth_derivative(x, K, torch.eye(4)[None], torch.ones_like(x))

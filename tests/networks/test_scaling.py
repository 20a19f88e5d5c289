"""Depth Scaling Layer and local scaling: analytic scale and field, frames without points, gradcheck."""

import math

import pytest
import torch

from endorecon.networks import (DepthScalingLayer, depth_scale, local_log_scale, scale_depth,
                                scale_depth_locally)


def test_analytic_scale_recovered():
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(3, 1, 8, 10, generator=g, dtype=torch.float64) + 0.5
    std = torch.full_like(depth, 0.1)
    true_scale = torch.tensor([2.0, 0.25, 7.5], dtype=torch.float64)
    sparse = depth * true_scale.view(-1, 1, 1, 1)
    valid = torch.rand(3, 1, 8, 10, generator=g) < 0.2
    valid[:, 0, 0, 0] = True
    sparse = torch.where(valid, sparse, torch.full_like(sparse, float("nan")))  # unused pixels may be NaN
    d, s, scale, has = scale_depth(depth, std, sparse, valid)
    torch.testing.assert_close(scale, true_scale)
    assert has.all()
    torch.testing.assert_close(d[valid], sparse[valid])
    torch.testing.assert_close(s, std * true_scale.view(-1, 1, 1, 1))


def test_ratio_of_sums_definition():
    depth = torch.tensor([1.0, 3.0]).view(1, 1, 1, 2)
    sparse = torch.tensor([2.0, 2.0]).view(1, 1, 1, 2)
    scale, _ = depth_scale(depth, sparse, torch.ones(1, 1, 1, 2, dtype=torch.bool))
    assert scale.item() == 1.0  # (2+2)/(1+3), not the mean ratio (2 + 2/3)/2


@pytest.mark.parametrize("mode", ["ratio_of_sums", "log_mean"])
def test_a_nan_prediction_at_a_point_leaves_only_that_point_out(mode):
    depth = torch.tensor([1.0, 1.0, float("nan")], dtype=torch.float64).view(1, 1, 1, 3)
    sparse = torch.full_like(depth, 2.0)
    scale, has = depth_scale(depth, sparse, torch.ones(1, 1, 1, 3, dtype=torch.bool), mode=mode)
    assert has.item() and scale.item() == pytest.approx(2.0)



@pytest.mark.parametrize("mode", ["ratio_of_sums", "log_mean"])
def test_a_non_finite_pixel_outside_the_loss_leaves_the_gradients_finite(mode):
    # one overflowed prediction (inf) where no loss looks: its value stays inf, but the scale's gradient
    # summed 0 * inf = NaN over every pixel and so made every sparse pixel's gradient NaN
    depth = (torch.rand(1, 1, 4, 5, dtype=torch.float64) + 0.5).requires_grad_()
    std = torch.full_like(depth, 0.1).requires_grad_()
    sparse = torch.full_like(depth, 2.0)
    valid = torch.zeros_like(depth, dtype=torch.bool)
    valid[..., 1, 1:4] = True
    bad = torch.where(torch.arange(20).view(1, 1, 4, 5) == 0, torch.tensor(float("inf"), dtype=depth.dtype), depth)
    d, s, scale, _ = scale_depth(bad, std, sparse, valid, mode=mode)
    assert torch.isinf(d[0, 0, 0, 0]) and torch.isfinite(scale).all()
    loss = ((d - sparse)[valid] ** 2).sum() + s[valid].sum()
    loss.backward()
    assert torch.isfinite(depth.grad).all() and torch.isfinite(std.grad).all()
    assert depth.grad[valid].abs().sum() > 0

def test_frames_without_points_keep_scale_one():
    depth = torch.full((2, 1, 4, 4), 2.0)
    sparse = torch.full_like(depth, 6.0)
    valid = torch.zeros(2, 1, 4, 4, dtype=torch.bool)
    valid[0, 0, 1, 1] = True
    d, s, scale, has = DepthScalingLayer()(depth, torch.ones_like(depth), sparse, valid)
    assert scale.tolist() == [3.0, 1.0] and has.tolist() == [True, False]
    assert (d[1] == 2.0).all() and (s[1] == 1.0).all()


def _gradcheck_inputs(seed, shape, density):
    """float64 depth, std, sparse depth (requiring grad) and a valid mask with ~``density`` of the pixels,
    the first pixel of every frame among them."""
    g = torch.Generator().manual_seed(seed)
    depth = (torch.rand(shape, generator=g, dtype=torch.float64) + 0.5).requires_grad_()
    std = (torch.rand(shape, generator=g, dtype=torch.float64) + 0.1).requires_grad_()
    sparse = (torch.rand(shape, generator=g, dtype=torch.float64) + 1).requires_grad_()
    valid = torch.rand(shape, generator=g) < density
    valid[:, 0, 0, 0] = True
    return depth, std, sparse, valid


@pytest.mark.parametrize("mode", ["ratio_of_sums", "log_mean"])
def test_gradcheck(mode):
    depth, std, sparse, valid = _gradcheck_inputs(1, (2, 1, 4, 5), 0.5)
    fn = lambda d, s, sp: scale_depth(d, s, sp, valid, mode=mode)[:2]  # noqa: E731
    assert torch.autograd.gradcheck(fn, (depth, std, sparse))


def test_log_mean_is_the_geometric_mean_of_the_ratios():
    depth = torch.tensor([1.0, 1.0, 5.0, 0.0]).view(1, 1, 1, 4)
    sparse = torch.tensor([2.0, 8.0, float("nan"), 3.0]).view(1, 1, 1, 4)
    valid = torch.tensor([True, True, False, True]).view(1, 1, 1, 4)  # the last: prediction 0, left out
    scale, has = depth_scale(depth, sparse, valid, mode="log_mean")
    assert scale.item() == pytest.approx(4.0) and has.all()  # sqrt(2 * 8); ratio_of_sums: 10 / 2 = 5
    assert depth_scale(depth, sparse, valid)[0].item() == pytest.approx(13.0 / 2.0)  # the 0 prediction counts there


def test_log_mean_recovers_a_known_scale_and_keeps_one_without_points():
    g = torch.Generator().manual_seed(2)
    depth = torch.rand(2, 1, 6, 7, generator=g, dtype=torch.float64) + 0.2
    sparse = depth * torch.tensor([3.0, 0.5], dtype=torch.float64).view(-1, 1, 1, 1)
    valid = torch.rand(2, 1, 6, 7, generator=g) < 0.3
    valid[0, 0, 0, 0] = True
    valid[1] = False
    d, s, scale, has = scale_depth(depth, torch.ones_like(depth), sparse, valid, mode="log_mean")
    torch.testing.assert_close(scale, torch.tensor([3.0, 1.0], dtype=torch.float64))
    assert has.tolist() == [True, False]
    torch.testing.assert_close(s[0], torch.full_like(s[0], 3.0))


def test_unknown_mode_is_an_error():
    depth = torch.ones(1, 1, 2, 2)
    with pytest.raises(ValueError, match="model.depth_scaling"):
        DepthScalingLayer(mode="median")(depth, depth, depth, depth > 0)


# ------------------------------------------------------------------ local scaling (inference only)
def _gauss(t, sigma):
    return math.exp(-(t**2) / (2 * sigma**2))


def test_local_field_of_one_point_is_the_weighted_log_ratio():
    sigma, prior = 2.0, 0.5
    depth = torch.full((1, 1, 21, 25), 2.0, dtype=torch.float64)
    sparse = torch.full_like(depth, float("nan"))
    valid = torch.zeros_like(depth, dtype=torch.bool)
    sparse[0, 0, 10, 12], valid[0, 0, 10, 12] = 6.0, True  # log ratio log 3
    field = local_log_scale(depth, sparse, valid, sigma, prior)
    for dy, dx in [(0, 0), (1, 0), (2, 3), (-4, 1)]:
        g = _gauss(math.hypot(dy, dx), sigma)
        assert field[0, 0, 10 + dy, 12 + dx].item() == pytest.approx(g * math.log(3) / (g + prior), rel=1e-12)
    assert field[0, 0, 10, 12 + 7].item() == 0.0  # beyond 3 sigma: the frame scale holds exactly
    assert field[0, 0, 0, 0].item() == 0.0


def test_local_field_inside_a_dense_constant_ratio():
    """Every pixel a point with ratio r: inside (3σ from the border) field = log r · G / (G + prior), G = (Σ_t g(t))²."""
    sigma, prior, r = 1.5, 2.0, 0.7
    depth = torch.rand(1, 1, 20, 20, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) + 1.0
    sparse = depth * r
    field = local_log_scale(depth, sparse, torch.ones_like(depth, dtype=torch.bool), sigma, prior)
    G = sum(_gauss(t, sigma) for t in range(-5, 6)) ** 2  # the kernel is cut at ceil(3 sigma) = 5
    torch.testing.assert_close(field[0, 0, 5:15, 5:15], torch.full((10, 10), math.log(r) * G / (G + prior),
                                                                    dtype=torch.float64))
    corner = field[0, 0, 0, 0].item()  # at the border fewer points: pulled harder towards the frame scale
    assert math.log(r) < corner < 0 and abs(corner) < abs(field[0, 0, 10, 10].item())


def test_local_scaling_depth_std_and_frames_without_points():
    g = torch.Generator().manual_seed(2)
    depth = torch.rand(2, 1, 12, 16, generator=g) + 0.5
    std = torch.rand(2, 1, 12, 16, generator=g) * 0.1 + 0.01
    sparse = torch.rand(2, 1, 12, 16, generator=g) + 0.5
    valid = torch.rand(2, 1, 12, 16, generator=g) < 0.1
    valid[1] = False  # frame 1: no point, unchanged
    valid[0, 0, 0, 0] = True
    d, s, field = scale_depth_locally(depth, std, sparse, valid, sigma_px=2.0, prior=0.5)
    assert torch.equal(d[1], depth[1]) and torch.equal(s[1], std[1]) and (field[1] == 0).all()
    torch.testing.assert_close(d / depth, torch.exp(field))
    torch.testing.assert_close(s / std, torch.exp(field))  # std stays relative to the depth
    # points whose SfM depth is NaN or not positive, or whose prediction is not positive, are left out
    ref = local_log_scale(depth, sparse, valid, 2.0, 0.5)
    sparse2, valid2, depth2 = sparse.clone(), valid.clone(), depth.clone()
    for (y, x), sd, dd in [((5, 5), float("nan"), 1.0), ((6, 6), -1.0, 1.0), ((7, 7), 2.0, 0.0)]:
        assert not valid[0, 0, y, x]
        sparse2[0, 0, y, x], valid2[0, 0, y, x], depth2[0, 0, y, x] = sd, True, dd
    torch.testing.assert_close(local_log_scale(depth2, sparse2, valid2, 2.0, 0.5), ref)


def test_local_field_leaves_out_outliers_beyond_max_log_ratio():
    """An outlier (log ratio far from its frame's median) is left out: the field is that of the other points."""
    sigma, prior = 2.0, 0.5
    depth = torch.full((2, 1, 15, 40), 2.0, dtype=torch.float64)
    sparse = torch.full_like(depth, float("nan"))
    valid = torch.zeros_like(depth, dtype=torch.bool)
    for x, r in [(5, 1.1), (12, 0.95), (20, 1.2), (28, 1.0), (35, 0.02)]:  # the last: 1/50 of the depth
        sparse[:, 0, 7, x], valid[:, 0, 7, x] = 2.0 * r, True
    valid[1, 0, 7, 35] = False  # frame 1: without the outlier
    field = local_log_scale(depth, sparse, valid, sigma, prior, max_log_ratio=0.5)
    torch.testing.assert_close(field[0], local_log_scale(depth, sparse, valid, sigma, prior)[1])
    assert field[0, 0, 7, 35].item() == 0.0  # the frame scale holds where only the outlier was
    # frame 1's median log ratio (the lower middle one of four) is log 1.0; the 1.2 point is 0.182 from it,
    # the 1.1 point 0.095: within 0.19 nothing is left out, within 0.1 the 1.2 point is
    torch.testing.assert_close(local_log_scale(depth, sparse, valid, sigma, prior, max_log_ratio=0.19)[1],
                               local_log_scale(depth, sparse, valid, sigma, prior)[1])
    tight = local_log_scale(depth, sparse, valid, sigma, prior, max_log_ratio=0.1)
    assert tight[1, 0, 7, 20].item() == 0.0 and tight[1, 0, 7, 5].item() > 0
    # without the threshold the outlier pulls the depth around it towards zero
    assert local_log_scale(depth, sparse, valid, sigma, prior)[0, 0, 7, 35].item() < math.log(0.02) / 1.5 + 1e-9
    # frames without any point: field 0, no NaN from the median
    assert (local_log_scale(depth, sparse, torch.zeros_like(valid), sigma, prior, max_log_ratio=0.5) == 0).all()


def test_local_scaling_gradcheck():
    depth, std, sparse, valid = _gradcheck_inputs(3, (2, 1, 6, 7), 0.3)
    fn = lambda d, s, sp: scale_depth_locally(d, s, sp, valid, 1.2, 0.5)[:2]  # noqa: E731
    assert torch.autograd.gradcheck(fn, (depth, std, sparse))
    fn = lambda d, s, sp: scale_depth_locally(d, s, sp, valid, 1.2, 0.5, max_log_ratio=0.2)[:2]  # noqa: E731
    assert torch.autograd.gradcheck(fn, (depth, std, sparse))


def test_local_scaling_checks_its_arguments():
    depth = torch.ones(1, 1, 4, 4)
    valid = torch.ones_like(depth, dtype=torch.bool)
    with pytest.raises(ValueError, match="sigma_px > 0 and prior > 0"):
        local_log_scale(depth, depth, valid, 0.0, 0.5)
    with pytest.raises(ValueError, match="sigma_px > 0 and prior > 0"):
        local_log_scale(depth, depth, valid, 2.0, 0.0)
    with pytest.raises(ValueError, match="sparse_depth"):
        local_log_scale(depth, torch.ones(1, 1, 4, 5), valid, 2.0, 0.5)
    for bad in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="max_log_ratio"):
            local_log_scale(depth, depth, valid, 2.0, 0.5, max_log_ratio=bad)

"""Depth Scaling Layer: analytic scale, frames without points, gradcheck."""

import pytest
import torch

from endorecon.networks import DepthScalingLayer, depth_scale, scale_depth


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


def test_frames_without_points_keep_scale_one():
    depth = torch.full((2, 1, 4, 4), 2.0)
    sparse = torch.full_like(depth, 6.0)
    valid = torch.zeros(2, 1, 4, 4, dtype=torch.bool)
    valid[0, 0, 1, 1] = True
    d, s, scale, has = DepthScalingLayer()(depth, torch.ones_like(depth), sparse, valid)
    assert scale.tolist() == [3.0, 1.0] and has.tolist() == [True, False]
    assert (d[1] == 2.0).all() and (s[1] == 1.0).all()


@pytest.mark.parametrize("mode", ["ratio_of_sums", "log_mean"])
def test_gradcheck(mode):
    g = torch.Generator().manual_seed(1)
    depth = (torch.rand(2, 1, 4, 5, generator=g, dtype=torch.float64) + 0.5).requires_grad_()
    std = (torch.rand(2, 1, 4, 5, generator=g, dtype=torch.float64) + 0.1).requires_grad_()
    sparse = (torch.rand(2, 1, 4, 5, generator=g, dtype=torch.float64) + 1).requires_grad_()
    valid = torch.rand(2, 1, 4, 5, generator=g) < 0.5
    valid[:, 0, 0, 0] = True
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

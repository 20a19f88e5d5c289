"""Flip averaging: mixture moments (analytic, sampled, gradcheck), the mirrored pass, shape checks."""

import pytest
import torch

from endorecon.networks import combine_predictions, predict_flip_averaged


def test_equal_predictions_are_unchanged():
    d = torch.rand(2, 1, 4, 5) + 0.5
    s = torch.rand(2, 1, 4, 5) * 0.1 + 0.01
    dd, ss = combine_predictions(d, s, d.clone(), s.clone())
    torch.testing.assert_close(dd, d)
    torch.testing.assert_close(ss, s)


def test_analytic_mixture_moments():
    # N(1, 0.3²) and N(3, 0.4²): mean 2, variance (0.09 + 0.16) / 2 + 1² = 1.125
    one = torch.ones(1, 1, 1, 1, dtype=torch.float64)
    d, s = combine_predictions(one, 0.3 * one, 3 * one, 0.4 * one)
    assert d.item() == pytest.approx(2.0)
    assert s.item() ** 2 == pytest.approx(1.125)


def test_moments_match_samples_of_the_mixture():
    g = torch.Generator().manual_seed(0)
    n = 400_000
    a = 1.0 + 0.2 * torch.randn(n, generator=g, dtype=torch.float64)
    b = 1.6 + 0.1 * torch.randn(n, generator=g, dtype=torch.float64)
    pick = torch.rand(n, generator=g) < 0.5
    x = torch.where(pick, a, b)
    v = torch.ones(1, 1, 1, 1, dtype=torch.float64)
    d, s = combine_predictions(1.0 * v, 0.2 * v, 1.6 * v, 0.1 * v)
    assert d.item() == pytest.approx(x.mean().item(), abs=2e-3)
    assert s.item() == pytest.approx(x.std().item(), abs=2e-3)


def test_gradcheck():
    g = torch.Generator().manual_seed(1)
    args = [torch.rand(1, 1, 3, 4, generator=g, dtype=torch.float64).add(0.2).requires_grad_() for _ in range(4)]
    assert torch.autograd.gradcheck(combine_predictions, args)


def test_mirrored_pass_is_mirrored_back():
    # a "network" whose depth is the pixel's column index + 1 whatever the image: the mirrored pass, mirrored
    # back, gives W - u, so the average is (W + 1) / 2 everywhere and the std holds the disagreement
    B, H, W = 2, 3, 6
    seen = []

    def net(img, mask):
        seen.append((img.clone(), None if mask is None else mask.clone()))
        u = torch.arange(W, dtype=img.dtype).view(1, 1, 1, W).expand(img.shape[0], 1, img.shape[2], W)
        return u + 1, torch.full_like(u, 0.5)

    img = torch.rand(B, 3, H, W)
    mask = torch.zeros(B, 1, H, W, dtype=torch.bool)
    mask[..., :2] = True
    d, s = predict_flip_averaged(net, img, mask)
    torch.testing.assert_close(d, torch.full((B, 1, H, W), (W + 1) / 2))
    u = torch.arange(W, dtype=torch.float32)
    half_gap = ((u + 1) - (W - u)) / 2
    torch.testing.assert_close(s[0, 0, 0], torch.sqrt(0.25 + half_gap**2))
    torch.testing.assert_close(seen[1][0], torch.flip(img, [-1]))  # the second pass sees the mirrored frame...
    torch.testing.assert_close(seen[1][1], torch.flip(mask, [-1]))  # ...and the mirrored mask
    d0, _ = predict_flip_averaged(net, img, None)  # no mask is allowed
    torch.testing.assert_close(d0, d)


def test_checks_shapes():
    d = torch.ones(1, 1, 4, 5)
    with pytest.raises(ValueError, match="std_b"):
        combine_predictions(d, d, d, torch.ones(1, 1, 4, 4))
    with pytest.raises(ValueError, match="depth_a"):
        combine_predictions(torch.ones(1, 4, 5), d, d, d)
    with pytest.raises(ValueError, match="mask"):
        predict_flip_averaged(lambda i, m: (d, d), torch.ones(1, 3, 4, 5), torch.ones(1, 1, 4, 4, dtype=torch.bool))

"""FC-DenseNet: sizes, positivity, std floor, parameter count, size checks."""

import pytest
import torch

from endorecon.networks import FCDenseNet, count_parameters

TINY = dict(first_conv_channels=8, growth_rate=4, down_layers=(1, 1, 1), bottleneck_layers=1, dropout=0.0)


def test_paper_configuration_parameter_count():
    # FC-DenseNet-57 with two 1x1 heads: the paper's implementation has ~1.37 M.
    n = count_parameters(FCDenseNet())
    assert 1.3e6 < n < 1.45e6


@pytest.mark.parametrize("hw", [(64, 80), (128, 160)])
def test_outputs_positive_with_floor(hw):
    torch.manual_seed(0)
    net = FCDenseNet(**TINY, std_floor=0.05)
    img = torch.rand(2, 3, *hw)
    mask = torch.ones(2, 1, *hw, dtype=torch.bool)
    depth, std = net(img, mask)
    assert depth.shape == std.shape == (2, 1, *hw)
    assert (depth > 0).all() and (std >= 0.05).all()
    with torch.no_grad():
        net.std_head.bias.fill_(-100.0)  # softplus -> 0: the floor remains
        assert torch.allclose(net(img, mask)[1], torch.full_like(std, 0.05))


def test_mask_zeroes_input():
    torch.manual_seed(0)
    net = FCDenseNet(**TINY).eval()
    img = torch.rand(1, 3, 32, 40)
    mask = torch.zeros(1, 1, 32, 40, dtype=torch.bool)
    mask[..., 8:24, 10:30] = True
    other = torch.where(mask, img, torch.rand_like(img))
    torch.testing.assert_close(net(img, mask)[0], net(other, mask)[0])


def test_size_not_divisible_raises_clear_message():
    net = FCDenseNet(**TINY)
    with pytest.raises(ValueError, match="divisible by 2\\*\\*levels = 8"):
        net(torch.rand(1, 3, 60, 80))


def test_bad_configuration():
    with pytest.raises(ValueError, match="std_floor"):
        FCDenseNet(**{**TINY, "std_floor": 0.0})
    with pytest.raises(ValueError, match="same non-zero length"):
        FCDenseNet(**{**TINY, "up_layers": (1, 1)})


def test_gradients_flow_to_all_parameters():
    torch.manual_seed(0)
    net = FCDenseNet(**TINY)
    d, s = net(torch.rand(2, 3, 32, 40))
    (d.mean() + s.mean()).backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_log_input_and_exp_depth():
    # log input: a frame twice as bright is the same input plus log 2 before normalisation; the exp head
    # starts at depth ~1 like the softplus one, and stays finite when its logit diverges
    torch.manual_seed(0)
    net = FCDenseNet(**TINY, input_transform="log", depth_activation="exp").eval()
    img = 0.05 + 0.4 * torch.rand(1, 3, 32, 40)
    x1, x2 = net.normalise(img, None), net.normalise(2 * img, None)
    torch.testing.assert_close(x2 - x1, torch.full_like(x1, float(torch.log(torch.tensor(2.0)))) / net.image_std)
    assert torch.isfinite(net.normalise(torch.zeros(1, 3, 32, 40), None)).all()  # clamped at 1/255
    depth, std = net(img)
    assert (depth - 1).abs().max() < 0.25 and (std > 0).all()
    with torch.no_grad():
        net.depth_head.bias.fill_(1e4)
        assert torch.isfinite(net(img)[0]).all()
    # log_centered: a per-channel gain of the frame changes nothing where the mask is on
    cen = FCDenseNet(**TINY, input_transform="log_centered").eval()
    mask = torch.zeros(1, 1, 32, 40)
    mask[..., 4:28, 5:35] = 1
    gain = torch.tensor([0.6, 1.3, 0.9]).view(1, 3, 1, 1)
    torch.testing.assert_close(cen.normalise(img * gain, mask), cen.normalise(img, mask))
    x = cen.normalise(img, mask) * cen.image_std + cen.image_mean * mask  # the centred log, inside the mask
    torch.testing.assert_close((x * mask).sum((2, 3)) / mask.sum(), torch.zeros(1, 3), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="input_transform"):
        FCDenseNet(**TINY, input_transform="gamma")
    with pytest.raises(ValueError, match="depth_activation"):
        FCDenseNet(**TINY, depth_activation="relu")


@pytest.mark.parametrize("train", [False, True])
def test_channels_last_is_the_same_network(train):
    """The memory layout is a speed option only: the same weights give the same depth, std and gradients in
    either layout, and a state dict saved in one loads into the other."""
    torch.manual_seed(0)
    cl = FCDenseNet(**TINY, channels_last=True)
    plain = FCDenseNet(**TINY, channels_last=False)
    plain.load_state_dict(cl.state_dict())
    assert cl.first_conv.weight.is_contiguous(memory_format=torch.channels_last)
    assert plain.first_conv.weight.is_contiguous()
    cl.train(train), plain.train(train)
    img = torch.rand(2, 3, 32, 40)
    mask = torch.rand(2, 1, 32, 40) > 0.2
    (d1, s1), (d2, s2) = cl(img, mask), plain(img, mask)
    assert d1.shape == d2.shape == (2, 1, 32, 40)
    torch.testing.assert_close(d1, d2, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(s1, s2, rtol=1e-5, atol=1e-6)
    (d1.mean() + s1.mean()).backward()
    (d2.mean() + s2.mean()).backward()
    for (name, p1), p2 in zip(cl.named_parameters(), plain.parameters()):
        torch.testing.assert_close(p1.grad, p2.grad, rtol=1e-4, atol=1e-6, msg=name)
    back = FCDenseNet(**TINY, channels_last=True)
    back.load_state_dict(plain.state_dict())
    assert back.first_conv.weight.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(back.first_conv.weight, plain.first_conv.weight)


def test_outputs_are_float32_under_autocast():
    """trainer=gpu trains in mixed precision: the heads' outputs stay float32 (the NLL losses' eps and squared
    residuals would not survive 16-bit), and are close to the full-precision ones."""
    torch.manual_seed(0)
    net = FCDenseNet(**TINY).eval()
    img = torch.rand(2, 3, 32, 40)
    with torch.no_grad():
        d32, s32 = net(img)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            d16, s16 = net(img)
            # the heads' convolutions did run in bfloat16 (else this test would not test the cast)
            assert net.depth_head(torch.rand(1, net.depth_head.in_channels, 4, 4)).dtype == torch.bfloat16
    assert d16.dtype == s16.dtype == torch.float32
    torch.testing.assert_close(d16, d32, rtol=0.05, atol=0.02)
    torch.testing.assert_close(s16, s32, rtol=0.05, atol=0.02)

"""Tests that mutations of endorecon/networks survived before (a review ran single-point mutations): each fails under its mutation."""

import torch

from endorecon.networks import predict_flip_averaged


def test_mirrored_pass_std_is_mirrored_back():
    """A 'network' whose std varies with the column and whose depth does not: the mirrored pass's std, mirrored
    back, must meet the first pass's at the same pixel (the existing check uses a constant std)."""
    B, H, W = 1, 2, 5

    def net(img, mask):
        u = torch.arange(W, dtype=img.dtype).view(1, 1, 1, W).expand(img.shape[0], 1, img.shape[2], W)
        # the std depends on the image content at that pixel: mirroring the image mirrors the std
        return torch.ones_like(u), 0.1 + img[:, :1].clone()

    img = torch.zeros(B, 3, H, W)
    img[..., 0] = 1.0  # left column bright: std 1.1 there, 0.1 elsewhere
    _, s = predict_flip_averaged(net, img, None)
    torch.testing.assert_close(s, 0.1 + img[:, :1])


def test_ratio_of_sums_frame_with_zero_predictions_at_its_points_keeps_scale_one():
    """Σ depth over the frame's points = 0 (predictions of 0 there): no scale can be had; scale 1 and
    has_sparse False, not inf/NaN that would poison the whole frame's depth and the batch's losses."""
    from endorecon.networks import depth_scale

    depth = torch.ones(2, 1, 4, 5)
    sparse = torch.full_like(depth, 3.0)
    valid = torch.zeros_like(depth, dtype=torch.bool)
    valid[:, 0, 1, 1] = valid[:, 0, 2, 3] = True
    depth[1, 0, 1, 1] = depth[1, 0, 2, 3] = 0.0
    scale, has = depth_scale(depth, sparse, valid, mode="ratio_of_sums")
    assert has.tolist() == [True, False]
    torch.testing.assert_close(scale, torch.tensor([3.0, 1.0]))

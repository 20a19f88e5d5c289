import numpy as np
import pytest
import torch

from endorecon.evaluation import depth_metrics, std_error_spearman


def _gt(n=3, h=8, w=10, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).uniform(5.0, 40.0, size=(n, h, w)))


def test_median_scaling_removes_a_global_factor():
    gt = _gt()
    m = depth_metrics(2.0 * gt, gt)
    for k in ("abs_rel", "sq_rel", "rmse", "rmse_log"):
        assert m[k] < 1e-12, k
    assert m["a1"] == m["a2"] == m["a3"] == 1.0
    assert m["scale_median"] == pytest.approx(0.5)
    assert m["n_frames"] == 3 and m["n_pixels"] == 3 * 8 * 10


def test_median_scaling_is_per_frame():
    gt = _gt()
    pred = gt * torch.tensor([0.1, 3.0, 7.0], dtype=torch.float64)[:, None, None]
    assert depth_metrics(pred, gt)["abs_rel"] < 1e-12
    assert depth_metrics(pred, gt, median_scaling=False)["abs_rel"] > 0.5


def test_relative_error_without_scaling():
    gt = _gt()
    e = 0.1
    m = depth_metrics(gt * (1 + e), gt, median_scaling=False)
    assert m["abs_rel"] == pytest.approx(e)
    assert m["sq_rel"] == pytest.approx(e**2 * gt.mean(dim=(1, 2)).mean().item())
    assert m["rmse"] == pytest.approx(e * gt.pow(2).mean(dim=(1, 2)).sqrt().mean().item())
    assert m["rmse_log"] == pytest.approx(np.log(1 + e))
    assert m["a1"] == 1.0
    m = depth_metrics(gt * 1.3, gt, median_scaling=False)  # 1.25 < 1.3 < 1.25²
    assert (m["a1"], m["a2"], m["a3"]) == (0.0, 1.0, 1.0)


def test_constant_offset():
    gt = _gt()
    m = depth_metrics(gt + 1.0, gt, median_scaling=False)
    assert m["abs_rel"] == pytest.approx((1.0 / gt).mean(dim=(1, 2)).mean().item())
    assert m["rmse"] == pytest.approx(1.0)


def test_valid_mask_cap_and_shapes():
    gt = _gt()
    pred = gt.clone()
    valid = torch.ones_like(gt, dtype=torch.bool)
    pred[:, :2] = 1000.0  # garbage rows, excluded by the mask
    valid[:, :2] = False
    m = depth_metrics(pred, gt, valid, median_scaling=False)
    assert m["abs_rel"] < 1e-12 and m["n_pixels"] == 3 * 6 * 10
    # gt = 0 is "no ground truth"; pixels beyond the cap are ignored.
    gt2 = gt.clone()
    gt2[:, 2] = 0.0
    m = depth_metrics(pred, gt2, valid, median_scaling=False)
    assert m["n_pixels"] == 3 * 5 * 10
    m = depth_metrics(gt * 1.1, gt, median_scaling=False, cap=20.0)
    assert m["n_pixels"] == int((gt <= 20).sum())
    # predictions are clamped to the cap: gt in (18.2, 20] is predicted at 20, not 1.1·gt
    expected = np.mean([((g[g <= 20] * 1.1).clamp(max=20) / g[g <= 20] - 1).mean().item() for g in gt])
    assert m["abs_rel"] == pytest.approx(expected) and expected < 0.099
    # (B, 1, H, W) torch and (N, H, W) numpy give the same numbers
    m1 = depth_metrics(1.7 * gt[:, None] + 0.3, gt[:, None], valid[:, None])
    m2 = depth_metrics((1.7 * gt + 0.3).numpy(), gt.numpy(), valid.numpy())
    assert m1 == m2


def test_frames_without_valid_pixels_are_skipped():
    gt = _gt()
    valid = torch.ones_like(gt, dtype=torch.bool)
    valid[1] = False
    assert depth_metrics(gt * 3, gt, valid)["n_frames"] == 2
    with pytest.raises(ValueError, match="no valid pixel"):
        depth_metrics(gt, gt, torch.zeros_like(valid))
    with pytest.raises(ValueError, match="differ in shape"):
        depth_metrics(gt[:, :4], gt)
    with pytest.raises(ValueError, match="must be"):
        depth_metrics(gt[:, None].expand(3, 2, 8, 10), gt[:, None].expand(3, 2, 8, 10))


def test_std_error_spearman():
    rng = np.random.default_rng(0)
    err = torch.from_numpy(rng.uniform(0, 1, size=(2, 1, 40, 50)))
    assert std_error_spearman(err**2 + 0.1, err) == pytest.approx(1.0)
    assert std_error_spearman(-err, err) == pytest.approx(-1.0)
    indep = torch.from_numpy(rng.uniform(0, 1, size=err.shape))
    assert abs(std_error_spearman(indep, err)) < 0.05
    # only valid pixels count: make the invalid half anti-correlated
    valid = torch.zeros_like(err, dtype=torch.bool)
    valid[..., :25] = True
    std = torch.where(valid, err, -err)
    assert std_error_spearman(std, err, valid) == pytest.approx(1.0)
    # subsampling keeps a monotone relation exact
    assert std_error_spearman(err + 1, err, max_samples=500) == pytest.approx(1.0)
    assert np.isnan(std_error_spearman(torch.ones_like(err), err))
    with pytest.raises(ValueError, match="at least 3"):
        std_error_spearman(err, err, torch.zeros_like(valid))


def test_depth_error_by_range_analytic():
    """Pixels at known relative depths with known biases: each bin reports its own share, sign and size."""
    from endorecon.evaluation import depth_error_by_range, format_depth_ranges

    # One frame: 2 pixels at 0.25x, 3 at 1x (the median), 1 at 4x the median GT depth.
    gt = torch.tensor([[[2.5, 2.5, 10.0, 10.0, 10.0, 40.0]]], dtype=torch.float64)
    # near walls 20 % too far, the far end half as deep, the middle exact; the median (1x) sets the scale
    pred = gt * torch.tensor([1.2, 1.2, 1.0, 1.0, 1.0, 0.5], dtype=torch.float64) * 7.0
    bins = depth_error_by_range(pred, gt, edges=(0, 0.5, 1.5, 3, float("inf")))
    assert [b["n_pixels"] for b in bins] == [2, 3, 0, 1]
    assert bins[0]["share"] == pytest.approx(2 / 6)
    assert bins[0]["log_error"] == pytest.approx(np.log(1.2)) and bins[0]["abs_rel"] == pytest.approx(0.2)
    assert bins[1]["log_error"] == pytest.approx(0.0, abs=1e-12)
    assert bins[2]["log_error"] is None and bins[2]["abs_rel"] is None
    assert bins[3]["log_error"] == pytest.approx(np.log(0.5)) and bins[3]["abs_rel"] == pytest.approx(0.5)
    assert bins[3]["hi"] is None  # inf is not standard JSON
    line = format_depth_ranges(bins)
    assert line.startswith("<0.5x +0.18 (33%)") and "1.5-3x n/a (0%)" in line and line.endswith(">3x -0.69 (17%)")
    # a mask leaves pixels out; without scaling the 7x shows
    valid = torch.tensor([[[True, True, True, True, True, False]]])
    b = depth_error_by_range(pred, gt, valid, edges=(0, 0.5, 1.5, 3, float("inf")), median_scaling=False)
    assert [x["n_pixels"] for x in b] == [2, 3, 0, 0] and b[1]["log_error"] == pytest.approx(np.log(7.0))
    with pytest.raises(ValueError, match="increasing"):
        depth_error_by_range(pred, gt, edges=(0, 1, 1))
    with pytest.raises(ValueError, match="no valid pixel"):
        depth_error_by_range(pred, gt, torch.zeros_like(valid))


def test_depth_error_by_range_plot(tmp_path):
    from endorecon.evaluation import depth_error_by_range
    from endorecon.evaluation.plots import save_depth_error_by_range

    gt = torch.tensor([[[2.5, 2.5, 10.0, 10.0, 10.0, 40.0]]], dtype=torch.float64)
    pred = gt * torch.tensor([1.2, 1.2, 1.0, 1.0, 1.0, 0.5], dtype=torch.float64)
    bins = depth_error_by_range(pred, gt)  # default bands, some empty
    out = save_depth_error_by_range(bins, tmp_path / "sub" / "by_range.png")
    import matplotlib.image as mpimg

    img = mpimg.imread(out)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100 and img[..., :3].std() > 0.01


def test_invalid_predictions_are_scored_not_dropped():
    """A network that gives NaN or 0 on its hard pixels must not score better for it."""
    gt = _gt()
    pred = gt.clone()
    pred[0, :4] = float("nan")  # 40 of 80 pixels of frame 0
    pred[1, :2] = 0.0
    m = depth_metrics(pred, gt)
    assert m["n_pixels"] == 3 * 8 * 10 and m["n_invalid_pred"] == 40 + 20
    assert m["abs_rel"] > 0.2 and m["a1"] < 0.9  # the floor is far off
    assert depth_metrics(gt.clone(), gt)["n_invalid_pred"] == 0


def test_median_scaling_uses_the_middle_of_an_even_count():
    gt = torch.tensor([[[1.0, 2.0, 3.0, 4.0]]], dtype=torch.float64)
    pred = torch.tensor([[[1.0, 1.0, 3.0, 3.0]]], dtype=torch.float64)
    # median(gt) = 2.5, median(pred) = 2.0 (torch.median would take 2 and 1)
    assert depth_metrics(pred, gt)["scale_median"] == pytest.approx(1.25)

"""Tests that mutations of endorecon/evaluation survived before (a review ran single-point mutations): each fails under its mutation."""

import numpy as np
import pytest
import torch

from endorecon.evaluation import ReferenceSurface, Sim3, depth_metrics, icp_sim3, register, sample_points
from endorecon.evaluation.registration import _best_of


def test_delta_thresholds_and_rmse_log_on_mixed_ratios():
    # one frame, four pixels with pred/gt = 1, 1.25 (exactly), 1.5, 3: delta < 1.25 is strict (KITTI convention)
    gt = torch.tensor([[[4.0, 4.0, 4.0, 4.0]]], dtype=torch.float64)
    pred = torch.tensor([[[4.0, 5.0, 6.0, 12.0]]], dtype=torch.float64)
    m = depth_metrics(pred, gt, median_scaling=False)
    assert m["a1"] == pytest.approx(1 / 4)  # only ratio 1 (1.25 is not < 1.25)
    assert m["a2"] == pytest.approx(3 / 4)  # 1, 1.25, 1.5 < 1.5625; 3 is not (nor < 2.5 either)
    m2 = depth_metrics(torch.tensor([[[4.0, 8.0]]], dtype=torch.float64), torch.tensor([[[4.0, 4.0]]], dtype=torch.float64),
                       median_scaling=False)
    assert m2["a2"] == pytest.approx(1 / 2)  # ratio 2 > 1.25**2 (would pass a 2.5 threshold)
    logs = np.log([1.0, 1.25, 1.5, 3.0])
    assert m["rmse_log"] == pytest.approx(np.sqrt((logs**2).mean()))  # RMS, not the mean |log|


def _truth_and_src(ct_mesh, recon_from_ct, n=3000):
    return recon_from_ct.inverse(), recon_from_ct.apply(sample_points(ct_mesh, n, seed=0))


def test_icp_scale_step_is_bounded_per_iteration(ct_mesh, recon_from_ct):
    truth, src = _truth_and_src(ct_mesh, recon_from_ct)
    init = Sim3(0.8, np.eye(3), np.zeros(3)) @ truth  # 20 % too small, otherwise exact
    init = Sim3(init.scale, init.R, init.t + (truth.apply(src).mean(0) - init.apply(src).mean(0)))
    res = icp_sim3(src, ReferenceSurface(ct_mesh), init, max_iter=1)
    step = np.log(res.ref_from_recon.scale / init.scale)
    assert 0 < step <= 0.05 + 1e-9, step  # towards the truth, by at most max_scale_step


def test_icp_scale_stays_within_slack(ct_mesh, recon_from_ct):
    truth, src = _truth_and_src(ct_mesh, recon_from_ct)
    init = Sim3(0.7, np.eye(3), np.zeros(3)) @ truth
    init = Sim3(init.scale, init.R, init.t + (truth.apply(src).mean(0) - init.apply(src).mean(0)))
    res = icp_sim3(src, ReferenceSurface(ct_mesh), init, scale_slack=1.1)
    ratio = res.ref_from_recon.scale / init.scale
    assert 1 / 1.1 - 1e-9 <= ratio <= 1.1 + 1e-9, ratio


def test_trajectory_init_limits_the_scale_change_to_25_percent(ct_mesh, recon_from_ct):
    rng = np.random.default_rng(0)
    truth, src = _truth_and_src(ct_mesh, recon_from_ct)
    v = np.asarray(ct_mesh.vertices)
    gt_centers = v.mean(0) + rng.normal(size=(20, 3)) * v.std(0) * 0.3
    # the reconstructed trajectory's scale is 1.6x off relative to its mesh: ICP may correct it by 25 % only
    c = recon_from_ct.apply(gt_centers)
    cam_centers = c.mean(0) + 1.6 * (c - c.mean(0))
    res = register(src, ReferenceSurface(ct_mesh), cam_centers=cam_centers, gt_cam_centers=gt_centers)
    s0 = truth.scale / 1.6
    assert res.init == "trajectory"
    assert res.ref_from_recon.scale <= 1.25 * s0 * (1 + 1e-9), (res.ref_from_recon.scale, s0)


def test_auto_init_prefers_the_trajectory_even_with_ref_points(ct_mesh, recon_from_ct):
    rng = np.random.default_rng(0)
    truth, src = _truth_and_src(ct_mesh, recon_from_ct)
    v = np.asarray(ct_mesh.vertices)
    gt_centers = v.mean(0) + rng.normal(size=(20, 3)) * v.std(0) * 0.3
    res = register(src, ReferenceSurface(ct_mesh), ref_points=sample_points(ct_mesh, 3000, seed=1),
                   cam_centers=recon_from_ct.apply(gt_centers), gt_cam_centers=gt_centers, global_trials=1)
    assert res.init == "trajectory"


def test_candidate_shrunk_onto_the_surface_does_not_win(ct_mesh, recon_from_ct):
    # The true alignment of a noisy reconstruction has ~0.3 mm median distance; a candidate that shrinks it
    # 1000x onto one vertex has smaller distances in mm but far larger ones in the reconstruction's units.
    rng = np.random.default_rng(3)
    truth, src = _truth_and_src(ct_mesh, recon_from_ct)
    src = src + rng.normal(scale=0.5 * recon_from_ct.scale, size=src.shape)
    c = truth.apply(src).mean(0)
    v0 = np.asarray(ct_mesh.vertices)[0]
    tiny = Sim3(1e-3, np.eye(3), v0 - 1e-3 * c) @ truth
    surface = ReferenceSurface(ct_mesh)
    assert np.median(surface.distance(tiny.apply(src))) < np.median(surface.distance(truth.apply(src)))  # not trivial
    res = _best_of(src, surface, [(tiny, None), (truth, None)], "global", 0, 4000, {"scale_slack": 2.0})
    assert res.extra["candidate"] == 1

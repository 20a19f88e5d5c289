"""Tests that mutations of endorecon/module survived before (a review ran single-point mutations): each fails under its mutation."""

from pathlib import Path

import torch
from omegaconf import OmegaConf

from endorecon.geometry import invert_pose
from endorecon.losses import dense_simulation_loss, depth_consistency_loss, sparse_depth_loss, sparse_flow_loss
from endorecon.module import DepthModule
from endorecon.networks import scale_depth, scale_depth_locally

from test_depth_module import _model_cfg, logged_panel_args, make_batch

CONF = Path(__file__).resolve().parents[2] / "conf"


def test_default_loss_weights_are_the_papers():
    """A partial cfg.loss (adapt passes only warmup_epochs) falls back on the paper's weights."""
    m = DepthModule(_model_cfg(), {"warmup_epochs": 1})
    assert m.weights == {"sparse_depth": 1.0, "depth_consistency": 0.5, "sparse_flow": 100.0,
                         "dense_simulation": 0.1}
    assert m.eps == 1e-8 and m.flow_std_floor == 1e-3
    assert DepthModule(_model_cfg()).warmup_epochs == 1


def test_loss_config_warmup_floor_and_trainer_clipping():
    """conf/loss/nll.yaml's non-weight entries and the trainer's gradient clipping (the module relies on it)."""
    m = DepthModule(OmegaConf.load(CONF / "model" / "fcdensenet_cpu.yaml"), OmegaConf.load(CONF / "loss" / "nll.yaml"))
    assert m.warmup_epochs == 1 and m.flow_std_floor == 1e-3
    trainer = OmegaConf.load(CONF / "trainer" / "cpu.yaml")
    assert trainer.gradient_clip_val == 1.0 and trainer.gradient_clip_algorithm == "norm"


def test_warmup_lasts_exactly_warmup_epochs():
    """in_warmup: epoch < warmup_epochs (epoch 0 with warmup_epochs 0 is not warm-up; the cfg value is used)."""
    assert not DepthModule(_model_cfg(), {"warmup_epochs": 0}).in_warmup()
    assert DepthModule(_model_cfg(), {"warmup_epochs": 1}).in_warmup()


class _Fixed(torch.nn.Module):
    """A deterministic 'network': smooth depth and std that differ per frame (no training noise)."""

    def forward(self, image, mask):
        d = 2.0 + image[:, :1] + 0.3 * image[:, 1:2]
        return d, 0.05 + 0.1 * image[:, 2:3]


def test_compute_losses_is_the_four_losses_in_both_directions():
    """Oracle: the module's losses equal the loss functions called on frames i with pose j<-i, masks i, j,
    the ij flows, and frames j with the inverse pose, masks j, i, the ji flows."""
    torch.manual_seed(0)
    b = make_batch(B=2)
    b["sparse_flow_valid_ji"][1] = False  # i's and j's flow validity differ
    b["mask_j"][..., :, :20] = False  # j's mask differs from i's
    b["cam_j_from_cam_i"][1, :3, 3] *= 0.5  # the two samples' poses differ
    b["has_sim"] = torch.tensor([True, False])
    b["sim_valid_i"][:, :, 10:30, 10:30] = True
    b["sim_valid_j"][:, :, 10:30, 10:30] = True
    b["sim_depth_i"][:] = 7.0
    b["sim_depth_j"][:] = 9.0
    m = DepthModule(_model_cfg(), {})
    m.net = _Fixed()
    with torch.no_grad():
        got = m.compute_losses(b)
    cat = lambda a, c: torch.cat([b[a], b[c]])  # noqa: E731
    d, s = m.net(cat("image_i", "image_j"), None)
    sv = cat("sparse_valid_i", "sparse_valid_j")
    d, s, _, _ = scale_depth(d, s, cat("sparse_depth_i", "sparse_depth_j"), sv)
    T = b["cam_j_from_cam_i"]
    T2, K2 = torch.cat([T, invert_pose(T)]), torch.cat([b["K"], b["K"]])
    mi, mj = b["mask_i"], b["mask_j"]
    swap = lambda x: torch.cat([x[2:], x[:2]])  # noqa: E731
    want = {
        "sparse_depth": sparse_depth_loss(d, s, cat("sparse_depth_i", "sparse_depth_j"), sv),
        "depth_consistency": depth_consistency_loss(d, s, swap(d), swap(s), K2, T2, torch.cat([mi, mj]),
                                                    mask_j=torch.cat([mj, mi])),
        "sparse_flow": sparse_flow_loss(d, s, K2, T2, cat("sparse_flow_ij", "sparse_flow_ji"),
                                        cat("sparse_flow_valid_ij", "sparse_flow_valid_ji")),
        "dense_simulation": dense_simulation_loss(
            d, s, cat("sim_depth_i", "sim_depth_j"),
            cat("sim_valid_i", "sim_valid_j") & torch.tensor([True, False, True, False]).view(4, 1, 1, 1)),
    }
    for k, v in want.items():
        torch.testing.assert_close(got[k], v, msg=k)
        assert got[k] > -50  # a real value, not an empty mean
    assert got["dense_simulation_active"].item() == 1.0


def test_predict_applies_the_configured_outlier_cut():
    """model.local_scaling.max_log_ratio reaches predict: a gross SfM outlier (1/50 of the depth) is left out."""
    ls = {"sigma_fraction": 0.1, "prior": 0.5, "max_log_ratio": 0.5}
    m = DepthModule(_model_cfg(depth_scaling="log_mean", local_scaling=ls))
    m.net = _Fixed()
    b = make_batch(B=1)
    img, mask = b["image_i"], b["mask_i"]
    with torch.no_grad():
        d0, _ = m.net(img, mask)
    sd = torch.zeros_like(d0)
    sv = torch.zeros_like(mask)
    for y, x in [(20, 20), (20, 40), (40, 30), (40, 60)]:
        sd[0, 0, y, x], sv[0, 0, y, x] = 3.0 * d0[0, 0, y, x], True
    sd[0, 0, 30, 50], sv[0, 0, 30, 50] = 0.06 * d0[0, 0, 30, 50], True  # the outlier
    d, _ = m.predict(img, mask, sd, sv)
    d1, s1, _, _ = scale_depth(d0, d0, sd, sv, mode="log_mean")
    sigma = 0.1 * img.shape[-1]
    cut, _, _ = scale_depth_locally(d1, s1, sd, sv, sigma, 0.5, max_log_ratio=0.5)
    uncut, _, _ = scale_depth_locally(d1, s1, sd, sv, sigma, 0.5)
    torch.testing.assert_close(d, cut)
    assert (d - uncut).abs().max() > 0.1



def test_a_non_finite_total_is_skipped_before_it_is_logged(tmp_path):
    """The training step's own skip of a non-finite total (the NaN-gradient check behind it would drop the step
    too, but only after the NaN was logged into the epoch's losses)."""
    import math

    from torch.utils.data import DataLoader

    from test_depth_module import _ParamsChanged, _trainer

    torch.manual_seed(0)
    module = DepthModule(_model_cfg(), {"warmup_epochs": 0})
    real, calls = module.compute_losses, []

    def losses(batch):
        out = real(batch)
        if len(calls) == 1:  # the second step: every loss NaN
            out = {k: v * float("nan") if torch.is_tensor(v) and v.is_floating_point() else v for k, v in out.items()}
        calls.append(1)
        return out

    module.compute_losses = losses
    rec = _ParamsChanged()
    trainer = _trainer(tmp_path, 3, [rec])
    trainer.fit(module, DataLoader([make_batch()] * 3, batch_size=None))
    assert rec.changed == [True, False, True] and module.skipped_batches == 1
    assert math.isfinite(float(trainer.callback_metrics["train/total_epoch"]))


def test_logged_panel_shows_the_networks_depth_with_its_non_finite_pixels_blank(tmp_path, monkeypatch):
    """The warp gets zero-filled depth (the losses' input rule); the depth panel gets the network's own, so a NaN
    pixel stays blank there instead of reading as depth 0 (which would also stretch the colour range)."""
    b = make_batch(B=1, scale=1.0)
    module = DepthModule(_model_cfg(log_images_every_n_steps=1))
    losses = module.compute_losses(b)
    depth = losses["depth"].detach().clone()
    depth[0, 0, 5, 7] = float("nan")
    args = logged_panel_args(module, b, {**losses, "depth": depth}, tmp_path, monkeypatch)
    shown, valid = args[2], args[6]
    assert torch.isnan(shown[0, 5, 7]) and not valid[0, 5, 7]
    finite = torch.isfinite(shown)
    assert torch.equal(shown[finite], depth[0][finite])

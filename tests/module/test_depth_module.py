"""DepthModule on a tiny synthetic pair batch: a tilted plane seen from two poses.

Sparse depth and sparse flow are computed analytically from the plane (ray-plane
intersection and projection) in the test.
"""

import math

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from endorecon.module import DepthModule
from endorecon.networks import FCDenseNet, combine_predictions, scale_depth, scale_depth_locally

H, W = 64, 80
TINY_NET = {
    "_target_": "endorecon.networks.FCDenseNet",
    "first_conv_channels": 8,
    "growth_rate": 4,
    "down_layers": [1, 1, 1],
    "bottleneck_layers": 1,
    "dropout": 0.0,
}


def _model_cfg(**kw):
    cfg = {
        "net": dict(TINY_NET),
        "optimizer": {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 3e-3},
        "scheduler": {"_target_": "torch.optim.lr_scheduler.OneCycleLR", "_partial_": True, "max_lr": 3e-3},
        "log_images_every_n_steps": 0,
    }
    cfg.update(kw)
    return cfg


def _plane_depth(K, n, c):
    """z-depth of the plane n·X = c at every pixel centre: z = c / (n · K⁻¹(u,v,1))."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)])
    return c / (n.view(3, 1, 1) * rays).sum(0), rays


def _sparse_flow(K, depth_a, rays, T_ba, valid):
    """Pixel displacement a -> b of the valid pixels: project T_ba·(depth·ray)."""
    X = depth_a * rays
    Xb = torch.einsum("ij,jhw->ihw", T_ba[:3, :3], X) + T_ba[:3, 3].view(3, 1, 1)
    u = K[0, 0] * Xb[0] / Xb[2] + K[0, 2]
    v = K[1, 1] * Xb[1] / Xb[2] + K[1, 2]
    gv, gu = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    flow = torch.stack([u - gu, v - gv])
    return torch.where(valid, flow, torch.zeros_like(flow))


def make_batch(B=2, seed=0, scale=3.0):
    """Frames i and j of the plane 0.2x + 0.1y + z = 5 (SfM units = ``scale`` × metric)."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[60.0, 0.0, 39.5], [0.0, 60.0, 31.5], [0.0, 0.0, 1.0]])
    n, c = torch.tensor([0.2, 0.1, 1.0]), 5.0
    a = 0.05
    T = torch.eye(4)
    T[0, 0], T[0, 2], T[2, 0], T[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    T[:3, 3] = torch.tensor([0.4, 0.1, 0.2])
    T_inv = torch.linalg.inv(T)
    depth_i, rays = _plane_depth(K, n, c)
    n_j = T[:3, :3] @ n  # plane in j: n_j·X = c + n_j·t
    depth_j, _ = _plane_depth(K, n_j, c + float(n_j @ T[:3, 3]))
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    mask[:, 4:-4, 4:-4] = True
    tex = torch.nn.functional.interpolate(torch.rand(1, 3, 8, 10, generator=g), size=(H, W), mode="bilinear")[0]
    batch = {k: [] for k in ("image_i", "image_j", "sparse_valid_i", "sparse_valid_j")}
    for _ in range(B):
        for key in batch:
            if key.startswith("image"):
                batch[key].append((tex + 0.05 * torch.rand(3, H, W, generator=g)).clamp(0, 1))
            else:
                batch[key].append((torch.rand(1, H, W, generator=g) < 0.02) & mask)
    batch = {k: torch.stack(v) for k, v in batch.items()}
    vi, vj = batch["sparse_valid_i"], batch["sparse_valid_j"]
    batch.update(
        mask_i=mask.expand(B, 1, H, W).clone(),
        mask_j=mask.expand(B, 1, H, W).clone(),
        K=K.expand(B, 3, 3).clone(),
        cam_j_from_cam_i=torch.cat([T[:3], torch.cat([T[3:, :3], T[3:, 3:]], 1)]).expand(B, 4, 4).clone(),
        sparse_depth_i=torch.where(vi, scale * depth_i, torch.zeros(())),
        sparse_depth_j=torch.where(vj, scale * depth_j, torch.zeros(())),
        sparse_flow_ij=torch.stack([_sparse_flow(K, depth_i, rays, T, vi[b]) for b in range(B)]),
        sparse_flow_ji=torch.stack([_sparse_flow(K, depth_j, rays, T_inv, vj[b]) for b in range(B)]),
        sparse_flow_valid_ij=vi.clone(),
        sparse_flow_valid_ji=vj.clone(),
        sim_depth_i=torch.zeros(B, 1, H, W),
        sim_depth_j=torch.zeros(B, 1, H, W),
        sim_valid_i=torch.zeros(B, 1, H, W, dtype=torch.bool),
        sim_valid_j=torch.zeros(B, 1, H, W, dtype=torch.bool),
        index_i=torch.arange(B),
        index_j=torch.arange(B) + 3,
        has_sim=torch.zeros(B, dtype=torch.bool),
    )
    # SfM poses are in SfM units too.
    batch["cam_j_from_cam_i"][:, :3, 3] *= scale
    return batch


class _Record(L.Callback):
    def __init__(self):
        self.losses = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.losses.append(None if outputs is None else float(outputs["loss"]))


def _trainer(tmp_path, steps, callbacks=(), **kw):
    return L.Trainer(
        default_root_dir=tmp_path, max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, callbacks=list(callbacks), gradient_clip_val=1.0, **kw,
    )  # fmt: skip


def test_synthetic_plane_fixture_is_consistent():
    """The analytic batch itself (not a loss): its sparse flow is the flow of the plane's GT depth, so that the
    tests that train on it train towards the true depth."""
    from endorecon.geometry import flow_from_depth

    b = make_batch(B=1, scale=1.0)
    depth_i, _ = _plane_depth(b["K"][0], torch.tensor([0.2, 0.1, 1.0]), 5.0)
    flow, _ = flow_from_depth(depth_i[None, None], b["K"], b["cam_j_from_cam_i"])
    v = b["sparse_flow_valid_ij"]
    torch.testing.assert_close(flow[v.expand(-1, 2, -1, -1)], b["sparse_flow_ij"][v.expand(-1, 2, -1, -1)])


def test_training_reduces_loss_without_nan(tmp_path):
    torch.manual_seed(0)
    module = DepthModule(_model_cfg(), {"warmup_epochs": 0})
    rec = _Record()
    batch = make_batch()
    with torch.no_grad():
        before = module.compute_losses(batch)
    _trainer(tmp_path, 30, [rec]).fit(module, DataLoader([batch] * 30, batch_size=None))
    assert None not in rec.losses and all(math.isfinite(x) for x in rec.losses)
    first, last = sum(rec.losses[:5]) / 5, sum(rec.losses[-5:]) / 5
    assert last < first - 0.1 * abs(first), (first, last)
    assert all(torch.isfinite(p).all() for p in module.parameters())
    with torch.no_grad():
        parts = module.compute_losses(batch)
    for k in ("sparse_depth", "depth_consistency", "sparse_flow"):  # each active loss goes down
        assert torch.isfinite(parts[k]) and parts[k] < before[k], (k, before[k], parts[k])
    assert parts["dense_simulation"].item() == 0.0 and parts["dense_simulation_active"].item() == 0.0


def test_loss_weights_and_warmup_honoured():
    torch.manual_seed(0)
    w = {"sparse_depth": 2.0, "depth_consistency": 0.3, "sparse_flow": 7.0, "dense_simulation": 0.5}
    module = DepthModule(_model_cfg(), {**w, "warmup_epochs": 2})
    batch = make_batch()
    batch["has_sim"][:] = True
    batch["sim_valid_i"][:, :, 10:20, 10:20] = True
    batch["sim_depth_i"][:] = 9.0
    with torch.no_grad():
        parts = module.compute_losses(batch)
    assert parts["dense_simulation_active"].item() == 1.0
    total_warm, shares_warm = module.total_loss(parts, warmup=True)
    assert set(shares_warm) == {"sparse_depth", "sparse_flow"}
    torch.testing.assert_close(total_warm, 2.0 * parts["sparse_depth"] + 7.0 * parts["sparse_flow"])
    total, shares = module.total_loss(parts, warmup=False)
    want = sum(w[k] * parts[k] for k in w)
    torch.testing.assert_close(total, want)
    assert module.in_warmup()  # current_epoch 0 < 2
    # has_sim = False switches the dense simulation loss off even with valid pixels.
    batch["has_sim"][:] = False
    with torch.no_grad():
        assert module.compute_losses(batch)["dense_simulation_active"].item() == 0.0


def test_losses_stay_float32_under_autocast():
    """Mixed precision (trainer=gpu) runs the network in 16 bits but not the geometry: the losses of a batch
    under bfloat16 autocast are the float32 ones up to the network's own rounding (the sparse flow loss, whose
    projections autocast would otherwise run in bfloat16, was ~3 % off on train_throughput.py's batch)."""
    torch.manual_seed(0)
    module = DepthModule(_model_cfg(), {"warmup_epochs": 0})
    batch = make_batch(B=2)
    with torch.no_grad():
        ref = module.compute_losses(batch)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed = module.compute_losses(batch)
    for k in ("sparse_depth", "depth_consistency", "sparse_flow"):
        assert mixed[k].dtype == torch.float32, k
        torch.testing.assert_close(mixed[k], ref[k], rtol=2e-3, atol=2e-3, msg=k)


def test_unknown_loss_key_rejected():
    with pytest.raises(ValueError, match="unknown cfg.loss keys"):
        DepthModule(_model_cfg(), {"sparse_flw": 1.0})


class _ParamsChanged(L.Callback):
    def __init__(self):
        self.changed = []

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        self._before = [p.detach().clone() for p in module.parameters()]

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.changed.append(any(not torch.equal(a, p) for a, p in zip(self._before, module.parameters())))


def test_non_finite_batch_is_skipped(tmp_path):
    torch.manual_seed(0)
    module = DepthModule(_model_cfg(), {"warmup_epochs": 0})
    good = make_batch()
    bad = make_batch()
    bad["image_i"][0, :, 20, 20] = float("nan")
    rec = _ParamsChanged()
    trainer = _trainer(tmp_path, 3, [rec])
    trainer.fit(module, DataLoader([good, bad, good], batch_size=None))
    assert rec.changed == [True, False, True]
    assert module.skipped_batches == 1
    assert all(torch.isfinite(p).all() for p in module.parameters())
    # the logged count is the running count (its epoch value the max, not a mean over the epoch's steps)
    assert float(trainer.callback_metrics["train/skipped_batches_epoch"]) == 1.0


def test_logged_skip_count_includes_steps_dropped_for_their_gradients(tmp_path):
    """A NaN gradient on the last batch drops the step in on_before_optimizer_step: it counts in the log too."""
    torch.manual_seed(0)
    module = DepthModule(_model_cfg(), {"warmup_epochs": 0})

    class NanGradOnLast(L.Callback):
        def on_after_backward(self, trainer, pl_module):
            if trainer.global_step == 3:
                next(pl_module.parameters()).grad[...] = float("nan")

    trainer = _trainer(tmp_path, 4, [NanGradOnLast()])
    trainer.fit(module, DataLoader([make_batch()] * 4, batch_size=None))
    assert module.skipped_batches == 1
    assert float(trainer.callback_metrics["train/skipped_batches_epoch"]) == 1.0


def test_non_finite_gradients_drop_the_step():
    module = DepthModule(_model_cfg(), {})
    params = list(module.parameters())
    for p in params:
        p.grad = torch.zeros_like(p)
    module.on_before_optimizer_step(None)
    assert module.skipped_batches == 0 and params[0].grad is not None
    params[3].grad[...] = float("nan")
    module.on_before_optimizer_step(None)
    assert module.skipped_batches == 1 and all(p.grad is None for p in params)


def test_checkpoint_round_trip_and_predict(tmp_path):
    torch.manual_seed(0)
    module = DepthModule(_model_cfg(), {"warmup_epochs": 0, "sparse_flow": 50.0})
    batch = make_batch()
    trainer = _trainer(tmp_path, 3)
    trainer.fit(module, DataLoader([batch] * 3, batch_size=None))
    module.skipped_batches = 4
    path = tmp_path / "m.ckpt"
    trainer.save_checkpoint(path)
    loaded = DepthModule.load_from_checkpoint(path)
    assert loaded.weights["sparse_flow"] == 50.0 and loaded.skipped_batches == 4
    assert isinstance(loaded.net, FCDenseNet)
    img, mask = batch["image_i"], batch["mask_i"]
    d0, s0 = module.predict(img, mask)
    d1, s1 = loaded.predict(img, mask)
    torch.testing.assert_close(d0, d1)
    torch.testing.assert_close(s0, s1)
    # Scaled prediction agrees with the sparse depth in the ratio-of-sums sense.
    d, s = loaded.predict(img, mask, batch["sparse_depth_i"], batch["sparse_valid_i"])
    v = batch["sparse_valid_i"]
    for b in range(img.shape[0]):
        ratio = batch["sparse_depth_i"][b][v[b]].sum() / d[b][v[b]].sum()
        assert ratio.item() == pytest.approx(1.0, rel=1e-5)
    torch.testing.assert_close(s / d, s1 / d1)  # std scales with depth
    assert loaded.training  # predict restores the mode


def test_validation_and_images_logged(tmp_path):
    from lightning.pytorch.loggers import TensorBoardLogger

    torch.manual_seed(0)
    module = DepthModule(_model_cfg(log_images_every_n_steps=1), {"warmup_epochs": 1})
    batch = make_batch()
    logger = TensorBoardLogger(tmp_path, name="tb")
    trainer = L.Trainer(
        default_root_dir=tmp_path, max_epochs=1, accelerator="cpu", logger=logger, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, log_every_n_steps=1, num_sanity_val_steps=0,
    )  # fmt: skip
    trainer.fit(module, DataLoader([batch] * 2, batch_size=None), DataLoader([batch], batch_size=None))
    m = trainer.callback_metrics
    for key in ("val/loss", "val/sparse_flow", "train/total_step", "train/sparse_depth_weighted_step",
                "train/depth_consistency_weighted_step", "train/skipped_batches_step", "train/lr"):
        assert key in m, (key, sorted(m))
    assert m["train/depth_consistency_weighted_step"].item() == 0.0  # warm-up epoch: weighted 0
    assert m["train/dense_simulation_step"].item() == 0.0
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ev = EventAccumulator(str(logger.log_dir))
    ev.Reload()
    assert "train/input_depth_std_sparse_error" in ev.Tags()["images"]


def _fit_and_reload(tmp_path, model_cfg, batch):
    """A DepthModule of ``model_cfg`` trained one step on ``batch``, saved and loaded back from its checkpoint."""
    module = DepthModule(model_cfg, {"warmup_epochs": 0})
    trainer = _trainer(tmp_path, 1)
    trainer.fit(module, DataLoader([batch], batch_size=None))
    trainer.save_checkpoint(tmp_path / "m.ckpt")
    return DepthModule.load_from_checkpoint(tmp_path / "m.ckpt")


@pytest.mark.parametrize("mode", ["ratio_of_sums", "log_mean"])
def test_depth_scaling_mode_is_used_and_kept_in_the_checkpoint(tmp_path, mode):
    torch.manual_seed(0)
    batch = make_batch()
    loaded = _fit_and_reload(tmp_path, _model_cfg(depth_scaling=mode), batch)
    assert loaded.scale_mode == mode
    img, mask, sd, sv = batch["image_i"], batch["mask_i"], batch["sparse_depth_i"], batch["sparse_valid_i"]
    d, _ = loaded.predict(img, mask, sd, sv)
    for b in range(img.shape[0]):
        r = sd[b][sv[b]] / d[b][sv[b]]
        geo = torch.exp(torch.log(r).mean()).item()
        assert (geo if mode == "log_mean" else sd[b][sv[b]].sum().item() / d[b][sv[b]].sum().item()) == \
            pytest.approx(1.0, rel=1e-5)
        if r.std() > 1e-3:  # the two estimators differ on this frame: the other one is not 1
            other = sd[b][sv[b]].sum().item() / d[b][sv[b]].sum().item() if mode == "log_mean" else geo
            assert other != pytest.approx(1.0, rel=1e-5)


def test_old_checkpoints_keep_the_ratio_of_sums():
    cfg = _model_cfg()
    assert "depth_scaling" not in cfg
    assert DepthModule(cfg).scale_mode == "ratio_of_sums"
    with pytest.raises(ValueError, match="depth_scaling"):
        DepthModule(_model_cfg(depth_scaling="median"))


def test_local_scaling_in_predict_only_and_kept_in_the_checkpoint(tmp_path):
    torch.manual_seed(0)
    ls = {"sigma_fraction": 0.1, "prior": 0.5, "max_log_ratio": 0.5}
    batch = make_batch()
    loaded = _fit_and_reload(tmp_path, _model_cfg(depth_scaling="log_mean", local_scaling=ls), batch)
    assert loaded.local_scaling == ls
    img, mask, sd, sv = batch["image_i"], batch["mask_i"], batch["sparse_depth_i"], batch["sparse_valid_i"]
    d, s = loaded.predict(img, mask, sd, sv)
    with torch.no_grad():
        d0, s0 = loaded.eval()(img, mask)
    d1, s1, _, _ = scale_depth(d0, s0, sd, sv, mode="log_mean")
    d2, s2, field = scale_depth_locally(d1, s1, sd, sv, 0.1 * img.shape[-1], 0.5, max_log_ratio=0.5)
    torch.testing.assert_close(d, d2)
    torch.testing.assert_close(s, s2)
    assert field.abs().max() > 1e-3  # the plane's points do move the depth here
    # the losses keep the paper's one scale per frame
    loaded.local_scaling = None
    out_off = loaded.compute_losses(batch)
    loaded.local_scaling = ls
    out_on = loaded.compute_losses(batch)
    torch.testing.assert_close(out_on["depth"], out_off["depth"])
    assert DepthModule(_model_cfg()).local_scaling is None  # checkpoints made before it: off
    assert DepthModule(_model_cfg(local_scaling={**ls, "enabled": False})).local_scaling is None
    assert DepthModule(_model_cfg(local_scaling={**ls, "enabled": True})).local_scaling == ls
    # no outlier test where the key is absent (checkpoints made before it) or null
    for cfg in ({"sigma_fraction": 0.1, "prior": 0.5}, {**ls, "max_log_ratio": None}):
        assert DepthModule(_model_cfg(local_scaling=cfg)).local_scaling == {**ls, "max_log_ratio": None}
    for bad in ({"sigma_fraction": 0.1}, {"sigma_fraction": 0.0, "prior": 0.5}, {"sigma": 1, "prior": 1},
                {**ls, "max_log_ratio": 0.0}, {**ls, "max_log_ratio": -0.5}):
        with pytest.raises(ValueError, match="local_scaling"):
            DepthModule(_model_cfg(local_scaling=bad))


def test_flip_average_in_predict_only_and_kept_in_the_checkpoint(tmp_path):
    torch.manual_seed(0)
    batch = make_batch()
    loaded = _fit_and_reload(tmp_path, _model_cfg(depth_scaling="log_mean", flip_average=True), batch)
    assert loaded.flip_average is True
    img, mask, sd, sv = batch["image_i"], batch["mask_i"], batch["sparse_depth_i"], batch["sparse_valid_i"]
    d, s = loaded.predict(img, mask, sd, sv)
    with torch.no_grad():
        da, sa = loaded.eval()(img, mask)
        db, sb = loaded(torch.flip(img, [-1]), torch.flip(mask, [-1]))
    d0, s0 = combine_predictions(da, sa, torch.flip(db, [-1]), torch.flip(sb, [-1]))
    d1, s1, _, _ = scale_depth(d0, s0, sd, sv, mode="log_mean")
    torch.testing.assert_close(d, d1)
    torch.testing.assert_close(s, s1)
    loaded.flip_average = False
    d_off, _ = loaded.predict(img, mask, sd, sv)
    assert (d_off - d).abs().max() > 1e-4  # the random network is not mirror-symmetric: the option did something
    out_off = loaded.compute_losses(batch)
    loaded.flip_average = True
    torch.testing.assert_close(loaded.compute_losses(batch)["depth"], out_off["depth"])  # losses: one pass
    assert DepthModule(_model_cfg()).flip_average is False  # checkpoints made before it: off
    with pytest.raises(ValueError, match="flip_average"):
        DepthModule(_model_cfg(flip_average="yes"))


@pytest.mark.parametrize("interval", ["step", "epoch"])
def test_one_cycle_anneals_over_the_run_in_its_interval(tmp_path, interval):
    """OneCycleLR's length is filled in from the run: in steps for a step-wise schedule, in epochs for an
    epoch-wise one (it was the number of batches for both: an epoch-wise cycle never annealed)."""
    lrs = []

    class Record(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            lrs.append(trainer.optimizers[0].param_groups[0]["lr"])

    module = DepthModule(_model_cfg(scheduler_interval=interval))
    trainer = L.Trainer(default_root_dir=tmp_path, max_epochs=5, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        callbacks=[Record()])
    trainer.fit(module, DataLoader([make_batch()] * 4, batch_size=None))
    sched = trainer.lr_scheduler_configs[0].scheduler
    assert sched.total_steps == (5 if interval == "epoch" else 20)
    assert max(lrs) > 0.5 * 3e-3 and lrs[-1] < 0.01 * 3e-3  # up to ~max_lr, then down to ~0 in the last steps


@pytest.mark.slow
def test_non_finite_batch_is_skipped_under_ddp(tmp_path):
    """Distributed training (trainer=ddp): a non-finite loss on one rank must skip that step on every rank
    and go on (returning None there stopped the whole fit: Lightning refuses it in distributed training)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).with_name("ddp_nonfinite_run.py")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parents[2])}
    run = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=300,
                         env=env, cwd=tmp_path)
    import re

    # the two ranks print at once: their lines can run together
    results = sorted(list(m) for m in re.findall(r"RESULT (\d+) (\d+) ([-+.\deE]+?)(?=RESULT|\s|$)", run.stdout))
    assert run.returncode == 0 and len(results) == 2, run.stdout[-2000:] + run.stderr[-3000:]
    assert [r[1] for r in results] == ["1", "1"]  # the step was skipped on both ranks
    assert results[0][2] == results[1][2]  # and the ranks' weights stayed the same


def test_logged_warp_error_panel_uses_frame_j_mask(tmp_path, monkeypatch):
    """A network exact inside both masks and wrong outside: the logged warped-pair error must be ~0, as the
    depth consistency loss sees it (j's depth outside j's mask was warped in: an error rim up to 40 %)."""
    b = make_batch(B=1, scale=1.0)
    K, T = b["K"][0], b["cam_j_from_cam_i"][0]
    n, c = torch.tensor([0.2, 0.1, 1.0]), 5.0
    d_i, _ = _plane_depth(K, n, c)
    n_j = T[:3, :3] @ n
    d_j, _ = _plane_depth(K, n_j, c + float(n_j @ T[:3, 3]))

    class Exact(torch.nn.Module):
        def forward(self, image, mask):
            d = torch.stack([d_i, d_j])[:, None]
            return torch.where(mask, d, torch.full_like(d, 3.0)), torch.full_like(d, 0.1)

    module = DepthModule(_model_cfg(log_images_every_n_steps=1))
    module.net = Exact()
    args = logged_panel_args(module, b, module.compute_losses(b), tmp_path, monkeypatch)
    rel, valid = args[5], args[6]
    assert valid.sum() > 100 and rel[valid].max() < 1e-3


def logged_panel_args(module, batch, losses, tmp_path, monkeypatch) -> tuple:
    """What ``module._log_images`` hands ``pair_panel`` (image, mask, depth, std, sparse, rel error, valid)."""
    from lightning.pytorch.loggers import TensorBoardLogger

    import endorecon.module.depth_module as dmod

    got = []

    def spy(*args):
        got.append(args)
        return torch.zeros(3, 4, 4)

    monkeypatch.setattr(dmod, "pair_panel", spy)
    module._trainer = L.Trainer(logger=TensorBoardLogger(str(tmp_path)), accelerator="cpu", enable_progress_bar=False)
    module._log_images(batch, losses, "train")
    assert len(got) == 1
    return got[0]

"""Test-time adaptation (endorecon.tasks.adapt): options, the loss goes down, weights restored when it does
not, the stage skips and reloads, and a checkpoint that load_module reads."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from endorecon.data.datamodule import PreparedSequence
from endorecon.data.sequence import Sequence
from endorecon.data.sparse import build_sparse_cache
from endorecon.module import DepthModule
from endorecon.tasks import adapt
from endorecon.utils.errors import InputError

H, W, N = 48, 64, 8
K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
NET = {"_target_": "endorecon.networks.FCDenseNet", "first_conv_channels": 8, "growth_rate": 4,
       "down_layers": [1, 1, 1], "bottleneck_layers": 1, "dropout": 0.0}
MODEL = {"net": NET, "log_images_every_n_steps": 0,
         "optimizer": {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 1e-3},
         "scheduler": {"_target_": "torch.optim.lr_scheduler.OneCycleLR", "_partial_": True, "max_lr": 3e-3}}
DATA = {"num_workers": 0, "augment": {"enabled": False}}
FAST = {"epochs": 2, "batches_per_epoch": 6, "batch_size": 2, "max_lr": 3e-3, "eval_batches": 3}


@pytest.fixture(scope="module")
def prepared(tmp_path_factory) -> list[PreparedSequence]:
    """A camera moving along a textured tunnel-like point cloud: frames, poses, SfM points."""
    root = tmp_path_factory.mktemp("video")
    rng = np.random.default_rng(0)
    paths = []
    for k in range(N):
        p = root / f"{k:03d}.png"
        Image.fromarray((rng.random((H, W, 3)) * 255).astype(np.uint8)).save(p)
        paths.append(p)
    T = np.stack([np.eye(4)] * N)
    T[:, 2, 3] = -0.3 * np.arange(N)
    P = 400
    X = np.stack([rng.uniform(-4, 4, P), rng.uniform(-3, 3, P), rng.uniform(6, 14, P)], 1)
    seq = Sequence(name="video", frame_paths=paths, intrinsics=K, height=H, width=W, mask=np.ones((H, W), bool),
                   cam_from_world=T, points_xyz=X, visibility=[np.arange(N)] * P, patient=0)
    return [PreparedSequence(seq=seq, cache=build_sparse_cache(seq))]


def module() -> DepthModule:
    torch.manual_seed(0)
    m = DepthModule(MODEL, {"warmup_epochs": 1})
    m.hparams["input_hw"] = [H, W]
    return m.eval()


@pytest.mark.parametrize("key,value", [("epochs", -1), ("batch_size", 0), ("max_lr", 0.0), ("max_lr", "x"),
                                       ("batches_per_epoch", 1.5), ("nonsense", 1)])
def test_bad_options_are_named(key, value):
    with pytest.raises(InputError, match=key):
        adapt._options({key: value})


def test_adaptation_lowers_the_video_loss_and_leaves_hparams(prepared):
    m = module()
    before = {k: v.clone() for k, v in m.state_dict().items()}
    hp_before = json.dumps(m.hparams["model"], sort_keys=True, default=str)
    info = adapt.adapt_module(m, DATA, prepared, FAST)
    assert info["kept"] and info["steps"] == 2 * 6
    assert np.isfinite(info["loss_before"]) and info["loss_after"] < info["loss_before"]
    assert adapt.video_loss(m, DATA, prepared, adapt._options(FAST)) == pytest.approx(info["loss_after"], rel=1e-5)
    assert any(not torch.equal(before[k], v) for k, v in m.state_dict().items())
    # the schedule override (max_lr) and the warm-up switch are temporary
    assert json.dumps(m.hparams["model"], sort_keys=True, default=str) == hp_before
    assert m.warmup_epochs == 1 and m._trainer is None and not m.training


def test_checkpoint_with_another_schedule_is_adapted(prepared):
    """A network trained with a schedule that takes no max_lr (cosine): adaptation crashed in
    configure_optimizers; it runs its own one-cycle schedule and leaves the checkpoint's hparams as they were."""
    torch.manual_seed(0)
    cosine = {**MODEL, "scheduler": {"_target_": "torch.optim.lr_scheduler.CosineAnnealingLR", "_partial_": True,
                                     "T_max": 100}, "scheduler_interval": "epoch"}
    m = DepthModule(cosine, {"warmup_epochs": 1})
    m.hparams["input_hw"] = [H, W]
    info = adapt.adapt_module(m.eval(), DATA, prepared, FAST)
    assert info["steps"] == 2 * 6 and np.isfinite(info["loss_after"])
    assert m.hparams["model"]["scheduler"]["_target_"].endswith("CosineAnnealingLR")
    assert m.hparams["model"]["scheduler_interval"] == "epoch"


def test_weights_restored_when_the_loss_does_not_go_down(prepared, monkeypatch):
    m = module()
    before = {k: v.clone() for k, v in m.state_dict().items()}
    losses = iter([1.0, 2.0])  # before, after: worse
    monkeypatch.setattr(adapt, "video_loss", lambda *a, **k: next(losses))
    info = adapt.adapt_module(m, DATA, prepared, {**FAST, "epochs": 1, "batches_per_epoch": 2})
    assert not info["kept"] and info["steps"] == 2
    assert all(torch.equal(before[k], v) for k, v in m.state_dict().items())


def test_zero_epochs_changes_nothing(prepared):
    m = module()
    before = {k: v.clone() for k, v in m.state_dict().items()}
    info = adapt.adapt_module(m, DATA, prepared, {**FAST, "epochs": 0})
    assert info["steps"] == 0 and not info["kept"]
    assert all(torch.equal(before[k], v) for k, v in m.state_dict().items())


def test_stage_writes_a_loadable_checkpoint_and_skips(prepared, tmp_path, monkeypatch):
    from endorecon.tasks.reconstruct import load_module

    m = module()
    ckpt, info, skipped = adapt.run(FAST, m, DATA, prepared, tmp_path / "adaptation", "stamp-1")
    assert not skipped and ckpt.is_file() and (tmp_path / "adaptation" / "adapt.json").is_file()
    assert json.loads((tmp_path / "adaptation" / "adapt.json").read_text())["steps"] == info["steps"]
    loaded, hw = load_module(ckpt)
    assert hw == (H, W)
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in m.state_dict().items())

    # same stamp: skipped, weights loaded from disk, no training
    monkeypatch.setattr(adapt, "adapt_module", lambda *a, **k: pytest.fail("a completed adaptation ran again"))
    fresh = module()
    ckpt2, info2, skipped2 = adapt.run(FAST, fresh, DATA, prepared, tmp_path / "adaptation", "stamp-1")
    assert skipped2 and ckpt2 == ckpt and info2["steps"] == info["steps"]
    assert all(torch.equal(fresh.state_dict()[k], v) for k, v in m.state_dict().items())
    # another input (or options): adapted again
    with pytest.raises(pytest.fail.Exception):
        adapt.run(FAST, module(), DATA, prepared, tmp_path / "adaptation", "stamp-2")
    with pytest.raises(pytest.fail.Exception):
        adapt.run({**FAST, "max_lr": 1e-3}, module(), DATA, prepared, tmp_path / "adaptation", "stamp-1")
    # other batches (augmentation, pair intervals): adapted again; the number of loader workers changes nothing
    for data in ({**DATA, "augment": {"enabled": True}}, {**DATA, "max_interval": 3}):
        with pytest.raises(pytest.fail.Exception):
            adapt.run(FAST, module(), data, prepared, tmp_path / "adaptation", "stamp-1")
    assert adapt.run(FAST, module(), {**DATA, "num_workers": 2}, prepared, tmp_path / "adaptation", "stamp-1")[2]


def test_disabled_stage_does_nothing(prepared, tmp_path):
    assert adapt.run({"enabled": False}, module(), DATA, prepared, tmp_path / "a", "s") == (None, None, False)
    assert not (tmp_path / "a").exists()


def test_video_without_pairs_is_a_clear_error(prepared, tmp_path):
    p = prepared[0]
    T = p.seq.cam_from_world.copy()
    T[1:] = np.nan  # one registered frame: no pair
    lone = [PreparedSequence(seq=p.seq.replace(cam_from_world=T), cache=p.cache)]
    with pytest.raises(InputError, match="adapt.enabled=false"):
        adapt.run(FAST, module(), DATA, lone, tmp_path / "a", "s")


def test_config_group_matches_the_code_defaults():
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    import endorecon.utils.resolvers  # noqa: F401

    conf = Path(__file__).resolve().parents[2] / "conf"
    for name in ("reconstruct", "train"):
        with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
            cfg = compose(config_name=name)
        assert adapt._options(cfg.adapt) == adapt.DEFAULTS, name


def test_corrupt_adapted_checkpoint_is_adapted_again(prepared, tmp_path):
    out = tmp_path / "adaptation"
    ckpt, _, _ = adapt.run(FAST, module(), DATA, prepared, out, "s")
    ckpt.write_bytes(b"not a checkpoint")  # e.g. a disk full while copying the run dir
    m = module()
    ckpt2, info, skipped = adapt.run(FAST, m, DATA, prepared, out, "s")
    assert not skipped and info["steps"] == FAST["epochs"] * FAST["batches_per_epoch"]
    assert all(torch.equal(torch.load(ckpt2, weights_only=False)["state_dict"][k], v) for k, v in m.state_dict().items())


def test_a_stop_between_the_checkpoint_and_its_record_is_not_taken_as_done(prepared, tmp_path, monkeypatch):
    """The adapted checkpoint is replaced before adapt.json: a stop in between left the old record beside the
    new weights, and a later run with the old options loaded weights adapted with other ones."""
    out = tmp_path / "adaptation"
    adapt.run(FAST, module(), DATA, prepared, out, "stamp-1")

    def stop(*a, **k):
        raise KeyboardInterrupt("stopped")

    monkeypatch.setattr(adapt, "atomic_write_text", stop)
    with pytest.raises(KeyboardInterrupt):
        adapt.run(FAST, module(), DATA, prepared, out, "stamp-2")  # new weights written, record not
    monkeypatch.undo()
    ran = []
    real = adapt.adapt_module
    monkeypatch.setattr(adapt, "adapt_module", lambda *a, **k: ran.append(1) or real(*a, **k))
    assert not adapt.run(FAST, module(), DATA, prepared, out, "stamp-1")[2] and ran == [1]

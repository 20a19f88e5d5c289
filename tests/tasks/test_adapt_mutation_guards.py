"""Mutation guards for the adaptation stage (endorecon/tasks/adapt.py).

Helpers and the ``prepared`` fixture come from test_adapt.py.  The first test runs each "adapted again"
check on its own copy of the finished stage, so that no check sees what an earlier one left."""

import math
import shutil

import pytest
import torch

from endorecon.tasks import adapt
from test_adapt import DATA, FAST, MODEL, module, prepared  # noqa: F401 - prepared is a fixture


def test_stage_stamp_covers_options_and_batches(prepared, tmp_path, monkeypatch):  # noqa: F811
    done = tmp_path / "done"
    m = module()
    adapt.run(FAST, m, DATA, prepared, done, "stamp-1")
    monkeypatch.setattr(adapt, "adapt_module", lambda *a, **k: pytest.fail("a completed adaptation ran again"))

    def again(opts, data, stamp="stamp-1"):
        d = tmp_path / f"copy{len(list(tmp_path.iterdir()))}"
        shutil.copytree(done, d)
        fresh = module()
        try:
            skipped = adapt.run(opts, fresh, data, prepared, d, stamp)[2]
        except pytest.fail.Exception:
            return False
        assert skipped and all(torch.equal(fresh.state_dict()[k], v) for k, v in m.state_dict().items())
        return True

    assert again(FAST, DATA) and again(FAST, {**DATA, "num_workers": 2})
    for opts, data, stamp in [(FAST, DATA, "stamp-2"), ({**FAST, "max_lr": 1e-3}, DATA, "stamp-1"),
                              ({**FAST, "seed": 1}, DATA, "stamp-1"), (FAST, {**DATA, "drop_last": True}, "stamp-1"),
                              (FAST, {**DATA, "max_interval": 3}, "stamp-1"),
                              (FAST, {**DATA, "augment": {"enabled": True}}, "stamp-1")]:
        assert not again(opts, data, stamp), (opts, data, stamp)


def test_spelled_out_default_augmentation_is_the_same_batches(prepared, tmp_path, monkeypatch):  # noqa: F811
    from endorecon.data.augment import AugmentConfig
    import dataclasses

    adapt.run(FAST, module(), DATA, prepared, tmp_path, "s")
    monkeypatch.setattr(adapt, "adapt_module", lambda *a, **k: pytest.fail("a completed adaptation ran again"))
    full = dataclasses.asdict(AugmentConfig.from_dict(DATA["augment"]))
    assert adapt.run(FAST, module(), {**DATA, "augment": full}, prepared, tmp_path, "s")[2]


@pytest.mark.parametrize("before, after, kept", [(float("nan"), 1.0, True), (float("nan"), float("nan"), False),
                                                 (1.0, float("nan"), False), (1.0, 1.0, False)])
def test_kept_only_when_the_loss_is_finite_and_lower(prepared, monkeypatch, before, after, kept):  # noqa: F811
    m = module()
    losses = iter([before, after])
    monkeypatch.setattr(adapt, "video_loss", lambda *a, **k: next(losses))
    orig = {k: v.clone() for k, v in m.state_dict().items()}
    info = adapt.adapt_module(m, DATA, prepared, {**FAST, "epochs": 1, "batches_per_epoch": 2})
    assert info["kept"] is kept
    assert all(torch.equal(orig[k], v) for k, v in m.state_dict().items()) is not kept


def test_max_lr_reaches_the_schedule_or_the_optimiser():
    assert adapt._with_max_lr(MODEL, 0.01)["scheduler"]["max_lr"] == 0.01
    plain = {k: v for k, v in MODEL.items() if k != "scheduler"}
    assert adapt._with_max_lr(plain, 0.02)["optimizer"]["lr"] == 0.02
    assert MODEL["scheduler"]["max_lr"] == 3e-3  # the checkpoint's own hparams untouched

"""Test-time self-supervised adaptation: a few epochs of the training losses on the video being reconstructed.

A fold's network never saw its held-out patient, and on the phantom it is
clearly worse there than on its training patients (fold 1: AbsRel 0.158
held out vs 0.048-0.093 on the patients it trained on).  The new video's own
SfM gives sparse depth and sparse flow, and its frame pairs give depth
consistency: the same self-supervised losses as training, no label.  This
stage fine-tunes a copy of the network on those pairs before inference.
Dense Simulation stays inactive (there is no fused mesh of the video yet).

Stage (hloc style): :func:`run` writes ``<out>/adapted.ckpt`` (a checkpoint
that :func:`endorecon.tasks.reconstruct.load_module` reads) and
``<out>/adapt.json`` (steps, seconds, the self-supervised loss on the video
before and after), and skips when both exist for the same input stamp.  If
the loss does not go down (or is not finite) the original weights are kept
and the report says so: an adaptation that made things worse is visible,
never silent.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import pickle
import time
from pathlib import Path

import numpy as np
import torch

from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_path, atomic_write_text

log = logging.getLogger(__name__)

__all__ = ["DEFAULTS", "adapt_module", "video_loss", "run"]

DEFAULTS = {
    "enabled": True,
    "epochs": 6,
    "batches_per_epoch": 60,
    "batch_size": 4,
    "max_lr": 1.0e-3,
    "eval_batches": 8,
    "seed": 0,
}


def _options(cfg_adapt) -> dict:
    c = dict(DEFAULTS)
    if cfg_adapt is not None:
        unknown = sorted(set(cfg_adapt) - set(DEFAULTS))
        if unknown:
            raise InputError(f"unknown adapt option(s) {unknown}", fix=f"use only {sorted(DEFAULTS)}")
        c.update({k: cfg_adapt[k] for k in cfg_adapt})
    for k in ("epochs", "batches_per_epoch", "batch_size", "eval_batches"):
        if not isinstance(c[k], int) or isinstance(c[k], bool) or c[k] < (0 if k == "epochs" else 1):
            raise InputError(f"adapt.{k} must be an integer >= {0 if k == 'epochs' else 1}, got {c[k]!r}",
                             fix=f"pass adapt.{k}={DEFAULTS[k]}")
    if not (isinstance(c["max_lr"], (int, float)) and math.isfinite(c["max_lr"]) and c["max_lr"] > 0):
        raise InputError(f"adapt.max_lr must be a positive number, got {c['max_lr']!r}", fix="pass adapt.max_lr=1e-3")
    return c


def _datamodule(data_cfg, prepared, opts: dict, augment: bool):
    from endorecon.data.datamodule import EndoDataModule

    seq = prepared[0].seq
    over = dict(height=seq.height, width=seq.width, batch_size=int(opts["batch_size"]), val_fraction=0.0,
                seed=int(opts["seed"]))
    if not augment:
        over["augment"] = {"enabled": False}
    try:
        return EndoDataModule(data_cfg, prepared, fold=None, patients_with_ct=[], **over)
    except InputError as e:
        fix = "pass adapt.enabled=false to reconstruct without adaptation"
        raise InputError(f"adaptation: {e.what}", e.path, f"{e.fix}; or {fix}" if e.fix else fix) from e


# The data keys that change the adaptation's batches (height, width, batch size, seed and the validation split
# are set by the adaptation itself; workers and the frame cache change nothing).
_DATA_KEYS = ("min_interval", "max_interval", "drop_last", "augment")


def _data_stamp(data_cfg) -> dict:
    from endorecon.data.augment import AugmentConfig
    from endorecon.data.datamodule import DEFAULTS as DATA_DEFAULTS

    if data_cfg is not None and not isinstance(data_cfg, dict):
        from omegaconf import OmegaConf

        data_cfg = OmegaConf.to_container(data_cfg, resolve=True)
    c = {**DATA_DEFAULTS, **(data_cfg or {})}
    # the augmentation as the data module completes it (a partial block takes the rest from the defaults)
    aug = dataclasses.asdict(AugmentConfig.from_dict(c["augment"]))
    return {k: (aug if k == "augment" else c[k]) for k in _DATA_KEYS}


@torch.no_grad()
def video_loss(module, data_cfg, prepared, opts: dict) -> float:
    """Mean total self-supervised loss (all weights, no warm-up) of ``module`` over the first
    ``opts['eval_batches']`` un-augmented pair batches of ``prepared`` (a fixed, seeded set)."""
    was_training = module.training
    module.eval()
    dm = _datamodule(data_cfg, prepared, opts, augment=False)
    device = next(module.parameters()).device
    totals = []
    for b, batch in enumerate(dm.train_dataloader()):
        if b >= int(opts["eval_batches"]):
            break
        batch = {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in batch.items()}
        total, _ = module.total_loss(module.compute_losses(batch), warmup=False)
        totals.append(float(total))
    module.train(was_training)
    return float(np.mean(totals)) if totals else float("nan")


def adapt_module(module, data_cfg, prepared, cfg_adapt=None) -> dict:
    """Fine-tune ``module`` in place on the pairs of ``prepared`` (the video's sequences, each a
    :class:`endorecon.data.datamodule.PreparedSequence`, all at one resolution).

    One-cycle learning rate up to ``max_lr``, ``epochs`` x ``batches_per_epoch`` batches of
    ``batch_size`` pairs, augmentation as in ``data_cfg``, no warm-up.  If the video's loss
    (:func:`video_loss`) is not lower afterwards, the weights are restored.
    Returns a dict: kept, steps, seconds, loss_before, loss_after, skipped_batches.
    """
    import lightning as L

    opts = _options(cfg_adapt)
    t0 = time.perf_counter()
    before = video_loss(module, data_cfg, prepared, opts)
    info = dict(kept=False, steps=0, seconds=0.0, loss_before=before, loss_after=before, skipped_batches=0)
    if int(opts["epochs"]) == 0:
        info["seconds"] = time.perf_counter() - t0
        return info
    original = copy.deepcopy(module.state_dict())
    hp_model = module.hparams["model"]
    module.hparams["model"] = _with_max_lr(hp_model, float(opts["max_lr"]))
    warmup, module.warmup_epochs = module.warmup_epochs, 0
    skipped0 = module.skipped_batches
    L.seed_everything(int(opts["seed"]), workers=True, verbose=False)
    trainer = L.Trainer(
        accelerator="gpu" if torch.cuda.is_available() else "cpu", devices=1, precision="32-true",
        max_epochs=int(opts["epochs"]), limit_train_batches=int(opts["batches_per_epoch"]),
        limit_val_batches=0, num_sanity_val_steps=0, gradient_clip_val=1.0, logger=False,
        enable_checkpointing=False, enable_model_summary=False,
        callbacks=[L.pytorch.callbacks.RichProgressBar(leave=False)],
    )
    module.train()  # load_module hands out eval mode: BatchNorm must learn the video's statistics
    try:
        trainer.fit(module, datamodule=_datamodule(data_cfg, prepared, opts, augment=True))
    finally:
        module.hparams["model"] = hp_model
        module.warmup_epochs = warmup
        module.trainer = None
    module.cpu()
    after = video_loss(module, data_cfg, prepared, opts)
    kept = bool(math.isfinite(after) and (not math.isfinite(before) or after < before))
    if not kept:
        log.warning("adaptation did not lower the video's self-supervised loss (%.4g -> %.4g): "
                    "keeping the network's original weights", before, after)
        module.load_state_dict(original)
    module.eval()
    info.update(kept=kept, steps=int(trainer.global_step), seconds=time.perf_counter() - t0, loss_after=after,
                skipped_batches=int(module.skipped_batches - skipped0))
    return info


def _with_max_lr(model_hp, max_lr: float):
    from omegaconf import DictConfig, OmegaConf

    m = OmegaConf.to_container(model_hp, resolve=True) if isinstance(model_hp, DictConfig) else copy.deepcopy(model_hp)
    one_cycle = "torch.optim.lr_scheduler.OneCycleLR"
    if m.get("scheduler") and m["scheduler"].get("_target_") == one_cycle:
        m["scheduler"]["max_lr"] = max_lr
    elif m.get("scheduler"):
        # another schedule takes no max_lr (CosineAnnealingLR crashed on it): the adaptation runs its own short
        # one-cycle schedule instead
        log.info("adaptation: a one-cycle schedule to max_lr %g in place of the checkpoint's %s", max_lr,
                 m["scheduler"].get("_target_"))
        m["scheduler"] = {"_target_": one_cycle, "_partial_": True, "max_lr": max_lr, "pct_start": 0.1}
        m["scheduler_interval"] = "step"
    elif m.get("optimizer"):
        m["optimizer"]["lr"] = max_lr
    return m


def run(cfg_adapt, module, data_cfg, prepared, out_dir: Path, stamp: str) -> tuple[Path | None, dict | None, bool]:
    """The adaptation stage: adapt ``module`` (in place) and write ``out_dir/adapted.ckpt`` + ``adapt.json``.

    Skipped (the saved weights are loaded into ``module``) when ``adapt.json`` exists with the same
    ``stamp`` (checkpoint, video, resolution), options and batch-making data keys (pair intervals,
    augmentation).
    Returns (adapted checkpoint, the ``adapt.json`` dict, skipped); (None, None, False) when disabled.
    """
    opts = _options(cfg_adapt)
    out_dir = Path(out_dir)
    ckpt, report = out_dir / "adapted.ckpt", out_dir / "adapt.json"
    if not opts["enabled"]:
        return None, None, False
    full_stamp = json.dumps({"input": stamp, "options": {k: opts[k] for k in sorted(opts)},
                             "data": _data_stamp(data_cfg)}, sort_keys=True)
    if report.is_file() and ckpt.is_file():
        try:
            done = json.loads(report.read_text())
            if done.get("stamp") == full_stamp:
                state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
                module.load_state_dict(state)
                module.eval()
                log.info("adaptation: %s is complete, skipping", ckpt)
                return ckpt, done, True
            log.info("adaptation was made for another checkpoint, video or options: adapting again")
        except (OSError, ValueError, KeyError, RuntimeError, EOFError, pickle.UnpicklingError) as e:  # corrupt output
            log.warning("unreadable adaptation output %s (%s): adapting again", out_dir, e)
    out_dir.mkdir(parents=True, exist_ok=True)
    info = adapt_module(module, data_cfg, prepared, opts)
    # the old record goes before the old weights do: a stop between the two writes below must not leave it
    # vouching for the new weights (a stop during the adaptation leaves both as they were)
    report.unlink(missing_ok=True)
    with atomic_path(ckpt) as tmp:
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                    "adaptation": info}, tmp)
    done = {**info, "options": opts, "stamp": full_stamp}
    atomic_write_text(report, json.dumps(done, indent=2) + "\n")
    log.info("adaptation: %d steps in %.0f s, video loss %.4g -> %.4g%s", info["steps"], info["seconds"],
             info["loss_before"], info["loss_after"], "" if info["kept"] else " (not kept)")
    return ckpt, done, False

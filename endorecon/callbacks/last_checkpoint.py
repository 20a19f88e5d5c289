"""``last.ckpt``: the state at the end of every training epoch, written atomically.

Lightning >= 2.6 writes ModelCheckpoint's ``save_last`` file only at a step where a top-k checkpoint
is saved too: with ``save_top_k=1`` on the validation loss, an epoch that does not improve it leaves
``last.ckpt`` at the previous best epoch.  Here that meant the next bootstrapping iteration warm-started,
and reconstruct.py ran, with weights one epoch older than the ones the iteration had evaluated.  This
callback writes the file after every epoch (validation included), whatever the monitored value did.
"""

from __future__ import annotations

import os
from pathlib import Path

import lightning as L


class LastCheckpoint(L.Callback):
    """Save ``<dirpath>/<filename>`` at every training epoch end (temp file + rename).

    Args:
        dirpath: folder of the file (train.py sets it to the iteration's ``checkpoints/``); None: the
            trainer's ``default_root_dir``/checkpoints.
        filename: name of the file.
    """

    def __init__(self, dirpath: str | None = None, filename: str = "last.ckpt"):
        self.dirpath = dirpath
        self.filename = filename

    def path(self, trainer: L.Trainer) -> Path:
        return Path(self.dirpath if self.dirpath is not None else Path(trainer.default_root_dir) / "checkpoints") / self.filename

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or trainer.fast_dev_run:
            return
        path = self.path(trainer)
        # the same temp name on every rank: save_checkpoint writes on rank 0 only
        tmp = path.with_name(f".{path.name}.partial")
        if trainer.is_global_zero:
            path.parent.mkdir(parents=True, exist_ok=True)
        trainer.save_checkpoint(tmp, weights_only=False)  # the full state: ckpt_path=last resumes from it
        if trainer.is_global_zero:
            os.replace(tmp, path)
        trainer.strategy.barrier()

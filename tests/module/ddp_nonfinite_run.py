"""Run by test_depth_module.py in a subprocess: two-process CPU DDP where rank 0's loss is NaN at step 1.

Prints one line per rank: ``RESULT <rank> <skipped batches> <parameter checksum>``."""

import sys
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

sys.path.insert(0, str(Path(__file__).parent))
from test_depth_module import _model_cfg, make_batch  # noqa: E402

from endorecon.module import DepthModule  # noqa: E402


class Pairs(Dataset):
    def __init__(self):
        self.batch = make_batch(B=1)

    def __len__(self):
        return 8

    def __getitem__(self, i):
        return {k: v[0] for k, v in self.batch.items()}


class NanOnRankZero(DepthModule):
    def total_loss(self, losses, warmup):
        total, shares = super().total_loss(losses, warmup)
        if self.training and self.global_rank == 0 and self.global_step == 1:
            total = total * float("nan")
        return total, shares


if __name__ == "__main__":
    torch.set_num_threads(1)
    cfg = _model_cfg()
    cfg.pop("scheduler")
    module = NanOnRankZero(cfg)
    trainer = L.Trainer(accelerator="cpu", devices=2, strategy="ddp", max_steps=4, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        gradient_clip_val=1.0, default_root_dir=sys.argv[1])
    trainer.fit(module, DataLoader(Pairs(), batch_size=1))
    checksum = sum(float(p.detach().double().sum()) for p in module.parameters())
    print(f"RESULT {trainer.global_rank} {module.skipped_batches} {checksum:.12e}", flush=True)

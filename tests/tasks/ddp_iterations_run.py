"""Run by test_train.py in a subprocess: two bootstrapping iterations of run_iteration on two-process CPU DDP
(gloo), with a tiny module and data module and no sequences (the end stage then only writes metrics.json).

argv[1]: the output root.  Prints ``RANK <r> iteration <i> done`` per rank and iteration."""

import os
import sys
import types
from pathlib import Path

import lightning as L
import torch
from hydra import compose, initialize_config_dir
from torch.utils.data import DataLoader, TensorDataset

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import endorecon.data.datamodule as datamodule  # noqa: E402
import endorecon.module as module  # noqa: E402
import endorecon.tasks.train as train  # noqa: E402
import endorecon.utils.resolvers  # noqa: E402, F401


class TinyData(L.LightningDataModule):
    def __init__(self, *a, **k):
        super().__init__()

    def train_dataloader(self):
        return DataLoader(TensorDataset(torch.randn(8, 3)), batch_size=2)

    def val_dataloader(self):
        return DataLoader(TensorDataset(torch.randn(4, 3)), batch_size=2)


class TinyModule(L.LightningModule):
    def __init__(self, model, loss):
        super().__init__()
        self.lin = torch.nn.Linear(3, 1)

    def training_step(self, batch, _):
        return self.lin(batch[0]).pow(2).mean()

    def validation_step(self, batch, _):
        self.log("val/loss", self.lin(batch[0]).pow(2).mean(), sync_dist=True)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


if __name__ == "__main__":
    torch.set_num_threads(1)
    datamodule.EndoDataModule = TinyData
    module.DepthModule = TinyModule
    train.prepare_sequences = lambda cfg, seqs, prev: []
    out = sys.argv[1]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[
            "trainer=ddp", "trainer.accelerator=cpu", "trainer.precision=32-true", "trainer.sync_batchnorm=false",
            "+trainer.enable_progress_bar=false", "callbacks.progress_bar=null", "bootstrap.epochs_per_iteration=1",
            f"paths.root_dir={out}", f"paths.run_dir='{out}/run'"])
    info = types.SimpleNamespace(root=out, patients_with_ct=[0])
    for it in (0, 1):
        train.run_iteration(cfg, it, [], info)
        print(f"RANK {os.environ.get('LOCAL_RANK', '0')} iteration {it} done", flush=True)

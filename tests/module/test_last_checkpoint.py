"""last.ckpt follows the trained weights at every epoch, whatever the validation loss does, and resumes."""

from __future__ import annotations

import lightning as L
import torch
from torch.utils.data import DataLoader, TensorDataset

from endorecon.callbacks import LastCheckpoint


class _Tiny(L.LightningModule):
    """A linear fit whose validation loss gets worse every epoch (so best-by-val stays at epoch 0)."""

    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(3, 1)

    def training_step(self, batch, _):
        x, y = batch
        return torch.nn.functional.mse_loss(self.lin(x), y)

    def validation_step(self, batch, _):
        self.log("val/loss", torch.tensor(float(self.current_epoch)))

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=1e-2)


def _loaders():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(32, 3, generator=g)
    y = x @ torch.tensor([[1.0], [-2.0], [0.5]])
    ds = TensorDataset(x, y)
    return DataLoader(ds, batch_size=8), DataLoader(ds, batch_size=16)


def _fit(root, max_epochs, ckpt_path=None):
    L.seed_everything(0)
    model = _Tiny()
    best = L.pytorch.callbacks.ModelCheckpoint(dirpath=str(root), filename="best-{epoch:03d}", monitor="val/loss",
                                               mode="min", save_top_k=1, save_last=False,
                                               auto_insert_metric_name=False)
    trainer = L.Trainer(max_epochs=max_epochs, callbacks=[best, LastCheckpoint(dirpath=str(root))], logger=False,
                        enable_progress_bar=False, enable_model_summary=False, accelerator="cpu", default_root_dir=str(root))
    train, val = _loaders()
    trainer.fit(model, train, val, ckpt_path=ckpt_path)
    return model, trainer, best


def test_last_checkpoint_holds_the_final_weights_when_validation_does_not_improve(tmp_path):
    model, trainer, best = _fit(tmp_path, 3)
    assert best.best_model_path.endswith("best-000.ckpt")  # never improved after epoch 0
    ck = torch.load(tmp_path / "last.ckpt", map_location="cpu", weights_only=False)
    assert ck["epoch"] == 2 and ck["global_step"] == trainer.global_step == 12
    for k, v in model.state_dict().items():
        assert torch.equal(ck["state_dict"][k], v)
    assert not list(tmp_path.glob(".*partial"))  # the temp file was renamed


def test_resume_from_last_matches_an_uninterrupted_run(tmp_path):
    full, _, _ = _fit(tmp_path / "full", 3)
    _fit(tmp_path / "cut", 2)  # "interrupted" after two epochs
    resumed, trainer, _ = _fit(tmp_path / "cut", 3, ckpt_path=str(tmp_path / "cut" / "last.ckpt"))
    assert trainer.global_step == 12
    for k, v in full.state_dict().items():
        assert torch.allclose(resumed.state_dict()[k], v, atol=1e-6)

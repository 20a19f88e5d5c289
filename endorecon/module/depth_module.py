"""DepthModule: the LightningModule that trains the depth-and-std network on frame pairs.

One step, for a batch of pairs (i, j) of one sequence (keys documented in
:data:`BATCH_KEYS`):

1. both frames go through the network in one batch of 2B images;
2. the Depth Scaling Layer brings each frame's depth and std to its SfM scale;
3. the four NLL losses of :mod:`endorecon.losses`, in both directions
   (i->j and j->i, as one batch of 2B):
   sparse depth, depth consistency, sparse flow, dense simulation;
4. total = Σ weight_k · loss_k.  During the first ``warmup_epochs`` only the
   sparse losses act (depth consistency and dense simulation are logged but
   weighted 0).  The validation total (``val/loss``, for checkpoint selection)
   always uses every weight so that epochs compare.

Robustness on CPU (NLL losses explode from a random init): a std floor in the
network, non-finite totals skip the batch (``training_step`` returns None),
non-finite gradients skip the optimizer step (grads dropped), both counted in
``train/skipped_batches``; gradient clipping is the trainer's
``gradient_clip_val``.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import hydra.utils
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from endorecon.geometry import invert_pose, warp_depth
from endorecon.losses import (
    consistency_inputs,
    dense_simulation_loss,
    depth_consistency_loss,
    sparse_depth_loss,
    sparse_flow_loss,
)
from endorecon.module.visuals import pair_panel
from endorecon.networks.flip import predict_flip_averaged
from endorecon.networks.scaling import check_scale_mode, scale_depth, scale_depth_locally

BATCH_KEYS = (
    "image_i", "image_j",  # (B,3,H,W) float [0,1]
    "mask_i", "mask_j",  # (B,1,H,W) bool
    "K",  # (B,3,3) pixel-centre
    "cam_j_from_cam_i",  # (B,4,4) SfM units
    "sparse_depth_i", "sparse_depth_j", "sparse_valid_i", "sparse_valid_j",  # (B,1,H,W), 0 = none / bool
    "sparse_flow_ij", "sparse_flow_valid_ij", "sparse_flow_ji", "sparse_flow_valid_ji",  # (B,2,H,W) / (B,1,H,W)
    "sim_depth_i", "sim_depth_j", "sim_valid_i", "sim_valid_j",  # (B,1,H,W) / bool
    "index_i", "index_j", "has_sim",  # (B,)
)  # fmt: skip

LOSS_NAMES = ("sparse_depth", "depth_consistency", "sparse_flow", "dense_simulation")
WARMUP_LOSSES = ("sparse_depth", "sparse_flow")

DEFAULT_LOSS = {
    "sparse_depth": 1.0,
    "depth_consistency": 0.5,
    "sparse_flow": 100.0,
    "dense_simulation": 0.1,
    "eps": 1e-8,
    "warmup_epochs": 1,
    "flow_std_floor": 1e-3,
}


def _plain(cfg: Any) -> dict:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    return dict(cfg or {})


def _local_scaling(cfg: Mapping | None) -> dict | None:
    """``model.local_scaling`` checked: None (off: null or ``enabled: false``) or dict(sigma_fraction > 0,
    prior > 0, max_log_ratio None or > 0; absent, as in older checkpoints: None)."""
    if cfg is None:
        return None
    cfg = dict(cfg)
    enabled = bool(cfg.pop("enabled", True))
    unknown = set(cfg) - {"sigma_fraction", "prior", "max_log_ratio"}
    if unknown or not {"sigma_fraction", "prior"} <= set(cfg):
        raise ValueError(f"model.local_scaling needs sigma_fraction and prior (and optionally enabled, max_log_ratio), "
                         f"or null; got {sorted(cfg)}")
    out = {k: float(cfg[k]) for k in ("sigma_fraction", "prior")}
    mlr = cfg.get("max_log_ratio")
    out["max_log_ratio"] = None if mlr is None else float(mlr)
    if not (out["sigma_fraction"] > 0 and out["prior"] > 0) or not (mlr is None or out["max_log_ratio"] > 0):
        raise ValueError(f"model.local_scaling.sigma_fraction and prior must be > 0 and max_log_ratio null or > 0, "
                         f"got {out}")
    return out if enabled else None


def _cat(batch: Mapping, a: str, b: str) -> torch.Tensor:
    return torch.cat([batch[a], batch[b]], 0)


class DepthModule(L.LightningModule):
    """Depth + std network trained with the four NLL losses.

    Args:
        model: ``cfg.model``: ``net`` (hydra ``_target_`` of the network, e.g.
            :class:`endorecon.networks.FCDenseNet`), ``optimizer`` and ``scheduler``
            (``_target_`` + ``_partial_: true``; OneCycleLR gets ``total_steps`` from the
            trainer if not given), ``scheduler_interval`` ("step"/"epoch"),
            ``log_images_every_n_steps`` (0 = never), ``depth_scaling`` (the Depth Scaling
            Layer's estimator, :data:`endorecon.networks.scaling.SCALE_MODES`; absent in
            checkpoints made before it existed: ``"ratio_of_sums"``, what those were trained with),
            ``local_scaling`` (null, or ``enabled``, ``sigma_fraction`` of the image width, ``prior`` and
            optionally ``max_log_ratio``, the outlier test, null or absent: off: the
            inference-only local scaling of :func:`endorecon.networks.scaling.scale_depth_locally`
            in :meth:`predict`; absent in older checkpoints: off), ``flip_average`` (bool: :meth:`predict`
            combines each frame's prediction with its mirror image's,
            :func:`endorecon.networks.flip.predict_flip_averaged`; absent in older checkpoints: off).
        loss: ``cfg.loss``: weights ``sparse_depth``, ``depth_consistency``, ``sparse_flow``,
            ``dense_simulation``; ``eps``; ``warmup_epochs``; ``flow_std_floor``.
    """

    def __init__(self, model: Mapping, loss: Mapping | None = None):
        super().__init__()
        model, loss = _plain(model), {**DEFAULT_LOSS, **_plain(loss)}
        if "net" not in model:
            raise ValueError("cfg.model needs a 'net' entry with a _target_ (e.g. endorecon.networks.FCDenseNet)")
        unknown = set(loss) - set(DEFAULT_LOSS)
        if unknown:
            raise ValueError(f"unknown cfg.loss keys {sorted(unknown)}; known: {sorted(DEFAULT_LOSS)}")
        self.save_hyperparameters({"model": model, "loss": loss})
        self.net = hydra.utils.instantiate(model["net"])
        self.weights = {k: float(loss[k]) for k in LOSS_NAMES}
        self.eps = float(loss["eps"])
        self.warmup_epochs = int(loss["warmup_epochs"])
        self.flow_std_floor = float(loss["flow_std_floor"])
        # checked here, not at the first batch: a typo fails before any data is loaded
        self.scale_mode = check_scale_mode(str(model.get("depth_scaling", "ratio_of_sums")))
        self.local_scaling = _local_scaling(model.get("local_scaling"))
        self.flip_average = model.get("flip_average", False)
        if not isinstance(self.flip_average, bool):
            raise ValueError(f"model.flip_average must be true or false, got {self.flip_average!r}")
        self.log_images_every_n_steps = int(model.get("log_images_every_n_steps", 0))
        self.skipped_batches = 0

    # ------------------------------------------------------------------ inference
    def forward(self, image: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Unscaled network output (depth, std), each (B,1,H,W)."""
        return self.net(image, mask)

    @torch.no_grad()
    def predict(
        self,
        images: torch.Tensor,
        mask: torch.Tensor,
        sparse_depth: torch.Tensor | None = None,
        sparse_valid: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Depth and std for inference/fusion, in eval mode (the previous mode is restored).

        Args:
            images: (B,3,H,W) in [0,1].  mask: (B,1,H,W) bool.
            sparse_depth, sparse_valid: optional (B,1,H,W); if given, the output is
                scaled to the SfM scale by the Depth Scaling Layer, then locally if
                ``model.local_scaling`` is set.  With ``model.flip_average`` the network's output is first
                averaged with that of the mirrored images.
        Returns:
            depth, std: (B,1,H,W).
        """
        was_training = self.training
        self.eval()
        try:
            if self.flip_average:
                depth, std = predict_flip_averaged(self.net, images, mask)
            else:
                depth, std = self.net(images, mask)
            if sparse_depth is not None:
                if sparse_valid is None:
                    sparse_valid = sparse_depth > 0
                depth, std, _, _ = scale_depth(depth, std, sparse_depth, sparse_valid, self.eps, self.scale_mode)
                if self.local_scaling is not None:
                    sigma_px = self.local_scaling["sigma_fraction"] * depth.shape[-1]
                    depth, std, _ = scale_depth_locally(depth, std, sparse_depth, sparse_valid, sigma_px,
                                                        self.local_scaling["prior"], self.eps,
                                                        self.local_scaling.get("max_log_ratio"))
        finally:
            self.train(was_training)
        return depth, std

    def predict_step(self, batch: Mapping, batch_idx: int = 0) -> dict:
        """Batch with ``image``, ``mask`` and optional ``sparse_depth``/``sparse_valid`` -> dict(depth, std)."""
        depth, std = self.predict(batch["image"], batch["mask"], batch.get("sparse_depth"), batch.get("sparse_valid"))
        return {"depth": depth, "std": std}

    # ------------------------------------------------------------------ losses
    def compute_losses(self, batch: Mapping) -> dict[str, torch.Tensor]:
        """Raw (unweighted) losses of a pair batch, both directions, plus diagnostics.

        Returns a dict with the four loss names (scalars), ``dense_simulation_active``
        (0/1), ``frames_without_sparse`` (count), and the scaled predictions
        ``depth``, ``std`` (2B,1,H,W) as [frames i; frames j].
        """
        missing = [k for k in BATCH_KEYS if k not in batch and k not in ("index_i", "index_j")]
        if missing:
            raise KeyError(f"batch lacks {missing}")
        image, mask = _cat(batch, "image_i", "image_j"), _cat(batch, "mask_i", "mask_j").bool()
        depth, std = self.net(image, mask)  # float32 also under autocast
        # Scaling, warps and losses in float32 also under mixed precision (trainer=gpu): autocast would run
        # the projections' matmuls in 16 bits, and bfloat16 pixel coordinates are ~0.5 px off at 100 px.
        with torch.autocast(depth.device.type, enabled=False):
            return self._losses(batch, depth, std, mask)

    def _losses(self, batch: Mapping, depth: torch.Tensor, std: torch.Tensor, mask: torch.Tensor) -> dict:
        sparse_depth = _cat(batch, "sparse_depth_i", "sparse_depth_j")
        sparse_valid = _cat(batch, "sparse_valid_i", "sparse_valid_j").bool()
        depth, std, _, has_sparse = scale_depth(depth, std, sparse_depth, sparse_valid, self.eps, self.scale_mode)

        T_ji = batch["cam_j_from_cam_i"].to(depth.dtype)
        T = torch.cat([T_ji, invert_pose(T_ji)], 0)  # i->j for frames i, j->i for frames j
        K = torch.cat([batch["K"], batch["K"]], 0).to(depth.dtype)
        B = batch["image_i"].shape[0]
        d_i, d_j = depth[:B], depth[B:]
        s_i, s_j = std[:B], std[B:]
        has_sim = batch["has_sim"].bool().view(-1, 1, 1, 1).repeat(2, 1, 1, 1)
        sim_valid = _cat(batch, "sim_valid_i", "sim_valid_j").bool() & has_sim
        out = {
            "sparse_depth": sparse_depth_loss(depth, std, sparse_depth, sparse_valid, self.eps),
            "depth_consistency": depth_consistency_loss(
                depth, std, torch.cat([d_j, d_i]), torch.cat([s_j, s_i]), K, T, mask, self.eps,
                mask_j=torch.cat([mask[B:], mask[:B]]),
            ),
            "sparse_flow": sparse_flow_loss(
                depth, std, K, T,
                _cat(batch, "sparse_flow_ij", "sparse_flow_ji"),
                _cat(batch, "sparse_flow_valid_ij", "sparse_flow_valid_ji").bool(),
                self.eps, flow_std_floor=self.flow_std_floor,
            ),  # fmt: skip
            "dense_simulation": dense_simulation_loss(
                depth, std, _cat(batch, "sim_depth_i", "sim_depth_j"), sim_valid, self.eps
            ),
            "dense_simulation_active": sim_valid.any().to(depth.dtype),
            "frames_without_sparse": (~has_sparse).sum().to(depth.dtype),
            "depth": depth,
            "std": std,
        }
        return out

    def in_warmup(self) -> bool:
        return self.current_epoch < self.warmup_epochs

    def total_loss(self, losses: Mapping[str, torch.Tensor], warmup: bool) -> tuple[torch.Tensor, dict]:
        """Σ weight·loss (warm-up: only the sparse losses); returns (total, weighted shares)."""
        shares = {}
        for k in LOSS_NAMES:
            if warmup and k not in WARMUP_LOSSES:
                continue
            if k == "dense_simulation" and not losses["dense_simulation_active"]:
                continue  # inactive: exactly zero, not 0·NaN
            shares[k] = self.weights[k] * losses[k]
        total = functools.reduce(torch.add, shares.values())
        return total, shares

    # ------------------------------------------------------------------ lightning hooks
    def training_step(self, batch: Mapping, batch_idx: int):
        losses = self.compute_losses(batch)
        warmup = self.in_warmup()
        total, shares = self.total_loss(losses, warmup)
        B = batch["image_i"].shape[0]
        log = functools.partial(self.log, on_step=True, on_epoch=True, batch_size=B)
        if not torch.isfinite(total):
            if self.trainer is not None and self.trainer.world_size > 1:
                # Lightning refuses a None from a distributed training step (the whole fit stopped): the
                # non-finite loss gives non-finite gradients, all-reduced to every rank, and
                # on_before_optimizer_step drops the step on all of them alike (and counts it)
                return total
            self.skipped_batches += 1
            return None
        for k in LOSS_NAMES:
            log(f"train/{k}", losses[k].detach())
            log(f"train/{k}_weighted", shares.get(k, torch.zeros_like(total)).detach())
        log("train/total", total.detach(), prog_bar=True)
        log("train/dense_simulation_active", losses["dense_simulation_active"])
        log("train/frames_without_sparse", losses["frames_without_sparse"])
        log("train/warmup", float(warmup))
        if self.trainer is not None and self.trainer.optimizers:
            log("train/lr", float(self.trainer.optimizers[0].param_groups[0]["lr"]), on_epoch=False)
        n = self.log_images_every_n_steps
        if n > 0 and self.global_step % n == 0:
            self._log_images(batch, losses, "train")
        return total

    def validation_step(self, batch: Mapping, batch_idx: int):
        losses = self.compute_losses(batch)
        total, shares = self.total_loss(losses, warmup=False)
        B = batch["image_i"].shape[0]
        log = functools.partial(self.log, on_step=False, on_epoch=True, batch_size=B)
        for k in LOSS_NAMES:
            log(f"val/{k}", losses[k])
            log(f"val/{k}_weighted", shares.get(k, torch.zeros_like(total)))
        log("val/loss", total, prog_bar=True)
        if batch_idx == 0 and self.log_images_every_n_steps > 0:
            self._log_images(batch, losses, "val")
        return total

    def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
        # after the optimizer step, so that a step dropped for its gradients counts too; a running count, so the
        # epoch value is its max (the default mean reported 0.17 for one skip at the last of 6 batches)
        self.log("train/skipped_batches", float(self.skipped_batches), on_step=True, on_epoch=True,
                 reduce_fx="max", batch_size=1)

    def on_before_optimizer_step(self, optimizer) -> None:
        grads = [p.grad for p in self.parameters() if p.grad is not None]
        if grads and not torch.isfinite(torch.stack([g.abs().sum() for g in grads])).all():
            self.skipped_batches += 1
            for p in self.parameters():
                p.grad = None  # optimizers skip params without grad: no step on this batch

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["skipped_batches"] = self.skipped_batches

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.skipped_batches = int(checkpoint.get("skipped_batches", 0))

    def configure_optimizers(self):
        model = self.hparams["model"]
        if "optimizer" not in model:
            return torch.optim.AdamW(self.parameters(), lr=1e-4)
        optimizer = hydra.utils.instantiate(model["optimizer"])(self.parameters())
        if not model.get("scheduler"):
            return optimizer
        make = hydra.utils.instantiate(model["scheduler"])
        kwargs = {}
        func = getattr(make, "func", None)
        interval = model.get("scheduler_interval", "step")
        if func is torch.optim.lr_scheduler.OneCycleLR and not ({"total_steps", "epochs"} & set(make.keywords)):
            # one cycle over the run, in the unit the scheduler steps in (an epoch-stepped cycle as long as the
            # run's batches never annealed)
            steps = self.trainer.max_epochs if interval == "epoch" else self.trainer.estimated_stepping_batches
            if steps is None or not (0 < steps < float("inf")):
                raise ValueError("OneCycleLR needs a finite schedule: set trainer max_epochs (max_steps for a "
                                 "step-wise schedule) or the scheduler's total_steps")
            kwargs["total_steps"] = int(steps)
        scheduler = make(optimizer, **kwargs)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": interval}}

    # ------------------------------------------------------------------ images
    @torch.no_grad()
    def _log_images(self, batch: Mapping, losses: Mapping, stage: str) -> None:
        from lightning.pytorch.loggers import TensorBoardLogger

        if not isinstance(self.logger, TensorBoardLogger):
            return
        B = batch["image_i"].shape[0]
        d_i, d_j = losses["depth"][:1].float(), losses["depth"][B : B + 1].float()
        # what the depth consistency loss compares (its own input rule): j's depth inside j's mask only (outside
        # it the network's output is unconstrained, and warping it in drew an error rim the loss never sees)
        s_i, s_j = losses["std"][:1].float(), losses["std"][B : B + 1].float()
        # (the warp gets the zero-filled copies; the panel shows the network's depth, its non-finite pixels blank)
        m_i, di0, dj0, _ = consistency_inputs(d_i, s_i, d_j, s_j, batch["mask_i"][:1], batch["mask_j"][:1])
        warped, valid, _ = warp_depth(dj0, di0, batch["K"][:1].float(), batch["cam_j_from_cam_i"][:1].float())
        valid = valid & m_i
        rel = torch.where(valid, (warped - di0).abs() / di0, torch.zeros_like(di0))
        panel = pair_panel(
            batch["image_i"][0], batch["mask_i"][0], d_i[0], losses["std"][0], batch["sparse_valid_i"][0], rel[0], valid[0]
        )
        self.logger.experiment.add_image(f"{stage}/input_depth_std_sparse_error", panel, self.global_step)

"""LightningModule of the depth network (losses, scaling, logging, optimisation)."""

from endorecon.module.depth_module import BATCH_KEYS, LOSS_NAMES, DepthModule

__all__ = ["BATCH_KEYS", "LOSS_NAMES", "DepthModule"]

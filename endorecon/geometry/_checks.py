"""Shape checks at the entry of geometry functions."""

from __future__ import annotations

import torch


def check_shape(x: torch.Tensor, name: str, shape: tuple) -> tuple[int, ...]:
    """Raise ``ValueError`` unless ``x`` is a tensor of ``shape`` (``None`` = any size). Returns ``x.shape``."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    return tuple(x.shape)

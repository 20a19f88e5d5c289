"""OmegaConf resolvers used by the configs (registered on import)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf


def _stem(path) -> str:
    return "unnamed" if path in (None, "None", "") else Path(str(path)).stem


if not OmegaConf.has_resolver("stem"):
    OmegaConf.register_new_resolver("stem", _stem)

"""OmegaConf resolvers used by the configs (registered on import)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf


def _stem(path) -> str:
    """The name of an input for its run dir: the file's stem, or the folder's name (``.`` and ``..`` resolved:
    their stems, '' and '..', put the outputs in the output root itself)."""
    if path in (None, "None", ""):
        return "unnamed"
    p = Path(str(path))
    if p.name in ("", ".", ".."):
        p = p.resolve()
    return p.stem or p.name or "unnamed"


if not OmegaConf.has_resolver("stem"):
    OmegaConf.register_new_resolver("stem", _stem)

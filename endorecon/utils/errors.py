"""User-facing errors.

Every error a user can cause by bad input is an :class:`InputError` that names
the offending file or config key and says what to do.  The task entry points
print these as one clean message (no traceback) and exit with status 2.
"""

from __future__ import annotations

import math
from pathlib import Path


class EndoreconError(RuntimeError):
    """Base class of errors that endorecon reports to the user without a traceback."""


class InputError(EndoreconError, ValueError):
    """Bad input: a missing/corrupt file, a wrong size, an unknown key.

    Args:
        what: what is wrong, e.g. ``"mask has size 100x100, frames are 256x320"``.
        path: the file or directory concerned (optional).
        fix: what the user should do about it (optional).
    """

    def __init__(self, what: str, path: str | Path | None = None, fix: str | None = None):
        self.what = what
        self.path = None if path is None else Path(path)
        self.fix = fix
        msg = what
        if path is not None:
            msg = f"{path}: {what}"
        if fix:
            msg += f"\n  fix: {fix}"
        super().__init__(msg)


def finite_number(value) -> float | None:
    """``value`` as a finite float, or None when it is not one (booleans, which YAML makes of ``yes``/``no``,
    are not numbers here)."""
    if isinstance(value, bool):
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def optional_number_above(value, key: str, lower: float, fix: str) -> float | None:
    """A setting that is null or a finite number above ``lower``: None or the float; else an :class:`InputError`
    naming ``key`` (:func:`finite_number`)."""
    if value is None:
        return None
    x = finite_number(value)
    if x is None or not x > lower:
        raise InputError(f"{key} must be a number > {lower:g} or null, got {value!r}", fix=fix)
    return x

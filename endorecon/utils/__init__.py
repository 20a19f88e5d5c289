"""Small shared helpers: user-facing errors, atomic file writes, logging."""

from endorecon.utils.errors import EndoreconError, InputError
from endorecon.utils.io import atomic_path, atomic_write_bytes, atomic_write_text, atomic_save_npz, atomic_dir

__all__ = [
    "EndoreconError",
    "InputError",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_save_npz",
    "atomic_dir",
]

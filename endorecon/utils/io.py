"""Atomic writes: every artifact is written to a temporary name and renamed.

A crash therefore never leaves a half-written file under its final name, and
stages can treat "the output file exists" as "the output is complete".
:func:`file_id` is what a stage records of an input file to tell, later, whether
its output was made from that same file.  :func:`read_json` reads a record a
stage wrote, turning a missing or damaged one into an :class:`InputError`.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from endorecon.utils.errors import InputError


def read_json(path: str | Path, fix: str) -> dict:
    """A JSON object written by a stage; a missing, unreadable or damaged file is an InputError naming it.

    Args:
        path: the file.
        fix: what the user should do (e.g. delete the run dir that holds it so that it is made again).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise InputError("the file is missing", path, fix) from e
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"cannot read it as JSON ({e})", path, fix) from e
    if not isinstance(data, dict):
        raise InputError(f"holds a JSON {type(data).__name__}, not an object", path, fix)
    return data


def _umask() -> int:
    old = os.umask(0)
    os.umask(old)
    return old


def _make_public(tmp: Path, directory: bool = False) -> None:
    """mkstemp / mkdtemp create 0600 / 0700; an artifact gets the permissions a plain open() would give."""
    os.chmod(tmp, (0o777 if directory else 0o666) & ~_umask())


def file_id(path: str | Path) -> dict:
    """An input file's identity for skip-if-done checks: resolved path, size and mtime (ns)."""
    st = Path(path).stat()
    return {"path": str(Path(path).resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


@contextlib.contextmanager
def file_lock(path: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (created if missing) while inside: jobs that share a cache (folds
    run in parallel) make it one after the other instead of writing the same files at once.  POSIX only;
    elsewhere it does nothing."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success.

    The temporary name keeps the final suffix (so libraries that pick a format
    from the extension, e.g. open3d or PIL, still work).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    _make_public(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def atomic_save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` to a temp file, then rename."""
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    return Path(path)


def remove_path(path: str | Path) -> None:
    """Delete a file or a whole directory; nothing if it is not there."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; rename it to ``path`` on success.

    An existing ``path`` is replaced only after the new one is complete.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    _make_public(tmp, directory=True)
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)

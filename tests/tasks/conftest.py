"""Fixtures of the task tests."""

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def debug_root(tmp_path_factory) -> Path:
    """A shared output root for the debug runs of this session (phantom and SfM caches reused)."""
    return tmp_path_factory.mktemp("endorecon_debug")

"""Fusion tests run torch single-threaded: on a shared, loaded 2-core machine a
parallel gather of a few hundred kB waits tens of ms for a descheduled worker."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread_torch():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)

"""Denoise tests run torch single-threaded: their tensors are tiny, and on the shared
2-core machine two OpenMP threads per process were measured 20x slower than one."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread_torch():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)

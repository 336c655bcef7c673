"""Shared pytest fixtures. Tests never touch ../shared/data and never download."""

import os

import numpy as np
import pytest

from mvgeo.common.threads import apply_thread_policy

os.environ.setdefault("DGS_NO_PROGRESS", "1")
# The command lines' OpenMP policy for the test process, before any test module loads torch.
apply_thread_policy()


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh seeded generator per test (tests are deterministic)."""
    return np.random.default_rng(20261121)


@pytest.fixture
def no_cuda(monkeypatch):
    """torch sees no CUDA device (for the `--device` checks, whatever this machine has)."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)

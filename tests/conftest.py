"""Shared pytest fixtures. Tests never touch ../shared/data and never download."""

import os

# Under pytest-xdist (`make test` runs one worker per core) each worker keeps to one thread in OpenMP and
# the BLAS libraries, so that the workers do not oversubscribe the cores; code that sets its
# own thread count (`mvgeo.common.threads.torch_threads`) still does. Set before numpy's BLAS and torch load.
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from mvgeo.common.threads import apply_thread_policy  # noqa: E402

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

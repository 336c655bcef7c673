"""Shared pytest fixtures. Tests never touch ../shared/data and never download."""

import os

import numpy as np
import pytest

os.environ.setdefault("DGS_NO_PROGRESS", "1")


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh seeded generator per test (tests are deterministic)."""
    return np.random.default_rng(20261121)

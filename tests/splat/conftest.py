"""Fixtures of the splat tests: tests that need the C++ kernels skip, with the reason, when the
kernels cannot be built here (no compiler: `CXX=/nonexistent`); the torch path is tested either way.

Two ways to ask for the kernels: the `cpp_kernel` fixture, or the `needs_cpp_kernel` mark (which
`pytest.param` accepts, e.g. `tests.splat.backends.BACKENDS`).
"""

from __future__ import annotations

import pytest

from splat import _cpu_kernel


def _skip_without_kernel() -> None:
    reason = _cpu_kernel.unavailable_reason()
    if reason is not None:
        pytest.skip(f"C++ splat kernels unavailable: {reason}")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "needs_cpp_kernel: skip (with the reason) when the C++ splat kernels "
                                       "cannot be built or loaded")


def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.get_closest_marker("needs_cpp_kernel") is not None:
        _skip_without_kernel()


@pytest.fixture
def cpp_kernel() -> None:
    """Skip the test when the C++ kernels are unavailable (the skip message says why)."""
    _skip_without_kernel()

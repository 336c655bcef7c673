"""The compositor backends of parametrized splat tests: "cpp" needs the C++ kernels and skips, with the
reason, without them (mark `needs_cpp_kernel`, tests/splat/conftest.py); "torch" always runs."""

import pytest

BACKENDS = [pytest.param("cpp", marks=pytest.mark.needs_cpp_kernel), "torch"]

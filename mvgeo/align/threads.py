"""Limit the threads of the OpenBLAS libraries numpy/scipy loaded (no extra dependency), and OpenCV's.

Why: the alignment already runs its pairwise work on a thread pool, and its bundle
adjustment makes thousands of small BLAS calls. With OpenBLAS's default (one
thread per core) the two oversubscribe the cores: on the shared 2-core machine the
bundle adjustment of llff_like 12 views took 2.0 s with one BLAS thread and
4.4-11.6 s with the default (measured, same inputs, same result).
"""

from __future__ import annotations

import ctypes
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_log = logging.getLogger(__name__)

#: (setter, getter) symbol names: upstream OpenBLAS, and the scipy-openblas wheels (64- and 32-bit ints).
_SYMBOLS = (("openblas_set_num_threads", "openblas_get_num_threads"),
            ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
            ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"))


def _loaded_openblas() -> list[tuple[ctypes._CFuncPtr, ctypes._CFuncPtr]]:
    """(set, get) functions of every OpenBLAS mapped into this process (Linux; elsewhere none)."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return []
    paths = sorted({line.split()[-1] for line in maps.read_text().splitlines()
                    if "openblas" in line.lower() and line.split()[-1].startswith("/")})
    out = []
    for p in paths:
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for set_name, get_name in _SYMBOLS:
            if hasattr(lib, set_name) and hasattr(lib, get_name):
                out.append((getattr(lib, set_name), getattr(lib, get_name)))
                break
    return out


@contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Run the block with at most `n` OpenBLAS threads (restored afterwards); `n <= 0`: unchanged."""
    libs = _loaded_openblas() if n > 0 else []
    old = []
    for setter, getter in libs:
        old.append(int(getter()))
        setter(int(n))
    try:
        yield
    finally:
        for (setter, _), k in zip(libs, old, strict=True):
            setter(k)


@contextmanager
def native_threads(n: int) -> Iterator[None]:
    """`blas_threads(n)` and OpenCV's own thread count (`cv2.setNumThreads`), both restored afterwards.

    OpenCV's SIFT and flow also start their own threads; inside the alignment's pool they
    oversubscribe the cores as BLAS does (measured ~4 % of the llff_like time at load ~3.5).
    """
    from mvgeo.common.deps import cv2

    old = cv2.getNumThreads()
    if n > 0:
        cv2.setNumThreads(int(n))
    try:
        with blas_threads(n):
            yield
    finally:
        cv2.setNumThreads(old)


def blas_thread_counts() -> list[int]:
    """Current thread count of every loaded OpenBLAS (for tests and logs)."""
    return [int(getter()) for _, getter in _loaded_openblas()]


__all__ = ["blas_thread_counts", "blas_threads", "native_threads"]

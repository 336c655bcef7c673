"""Scoped thread limits for torch, the BLAS libraries numpy/scipy load, and OpenCV (all restored afterwards).

Why: on a small shared machine, nested or concurrent thread pools oversubscribe the
cores. Measured on 2 cores (docs/benchmarks.md): the alignment's bundle adjustment of
llff_like 12 views took 2.0 s with one BLAS thread and 4.4-11.6 s with OpenBLAS's
default, inside the alignment's own pool; splat training with 2 torch threads ran up
to ~20x slower than with 1 at load ~4. BLAS limits go through `threadpoolctl`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import ThreadpoolController, threadpool_limits


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with `max(1, n)` torch intra-op threads; None: unchanged."""
    import torch

    saved = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(saved)


@contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Run the block with at most `n` threads in every loaded BLAS; `n <= 0`: unchanged."""
    if n <= 0:
        yield
        return
    with threadpool_limits(limits=int(n), user_api="blas"):
        yield


@contextmanager
def native_threads(n: int) -> Iterator[None]:
    """`blas_threads(n)` and OpenCV's own thread count (`cv2.setNumThreads`); `n <= 0`: unchanged.

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
    """Current thread count of every loaded BLAS (for tests and logs)."""
    return [int(info["num_threads"]) for info in ThreadpoolController().select(user_api="blas").info()]


__all__ = ["blas_thread_counts", "blas_threads", "native_threads", "torch_threads"]

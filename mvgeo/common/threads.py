"""Scoped thread limits for torch, the BLAS libraries numpy/scipy load, and OpenCV (all restored afterwards).

Why: on a small shared machine, nested or concurrent thread pools oversubscribe the
cores. Measured on 2 cores (docs/benchmarks.md): the alignment's bundle adjustment of
llff_like 12 views took 2.0 s with one BLAS thread and 4.4-11.6 s with OpenBLAS's
default, inside the alignment's own pool; splat training with 2 torch threads ran up
to ~20x slower than with 1 at load ~4. BLAS limits go through `threadpoolctl`.

The process-wide part, the OpenMP wait policy, is `apply_thread_policy`: the command
lines call it before torch loads; library users call it (or export the variable)
themselves, before importing torch. Importing this module changes nothing: torch, cv2
and threadpoolctl (which sets `KMP_DUPLICATE_LIB_OK` when imported) load on first use.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

_log = logging.getLogger(__name__)

#: The OpenMP wait policy the command lines use unless the environment already sets one.
OMP_WAIT_POLICY_DEFAULT = "PASSIVE"

#: Modules that load an OpenMP runtime (torch's libgomp); the runtime reads `OMP_WAIT_POLICY`
#: once, when it loads, so the variable must be set before the first of them is imported.
_OPENMP_MODULES = ("torch",)


def apply_thread_policy() -> bool:
    """Set the process-wide OpenMP wait policy: `OMP_WAIT_POLICY=PASSIVE` unless already set.

    With OpenMP's default (spinning) policy, torch's idle intra-op threads busy-wait between the
    many small ops of a training step; on a loaded 2-core machine that made N2V training 1.7x
    slower with 2 threads than with 1 and splat training up to ~20x slower, while with `PASSIVE`
    the same 2-thread N2V run was 3.7x faster than spinning (docs/benchmarks.md, "Threads").

    Every console script calls this before its imports load torch. A library user who wants the
    same behaviour calls it first thing (before `import torch` or any `splat`/`denoise`/`eval`
    module that imports torch), or exports `OMP_WAIT_POLICY=PASSIVE` in the shell. A value the
    user set is kept. Torch's thread count is not changed here; scope it with `torch_threads`.

    Returns:
        True when the policy is in force: the variable was set before an OpenMP runtime loaded
        (or the user's own value is kept). False, with a warning, when torch was already
        imported and the variable was not set: the running runtime ignores it (child processes
        inherit it).
    """
    if "OMP_WAIT_POLICY" in os.environ:
        return True
    os.environ["OMP_WAIT_POLICY"] = OMP_WAIT_POLICY_DEFAULT
    loaded = [m for m in _OPENMP_MODULES if m in sys.modules]
    if loaded:
        _log.warning("OMP_WAIT_POLICY=%s was set after %s loaded its OpenMP runtime, which ignores it; "
                     "call apply_thread_policy() before importing %s, or export the variable",
                     OMP_WAIT_POLICY_DEFAULT, loaded[0], loaded[0])
        return False
    return True


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


def pool_threads(workers: int | None = None, items: int | None = None) -> int:
    """Threads of a pool over independent pieces of work (pairs, views, files): `workers` when given (> 0),
    else torch's current intra-op thread count, the threads the caller runs with: the cores by default
    (`OMP_NUM_THREADS` where set), the CPUs Ray gives a task (`eval.distributed`, one by default), so that
    N one-CPU tasks on N cores do not run N pools of one thread per core. The machine's cores where torch
    is not loaded (nothing has scoped its threads). At most `items` when given; at least 1.
    """
    if workers is not None and workers > 0:
        n = int(workers)
    else:
        torch = sys.modules.get("torch")
        n = torch.get_num_threads() if torch is not None else (os.cpu_count() or 1)
    return max(1, min(n, items) if items is not None else n)


@contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Run the block with at most `n` threads in every loaded BLAS; `n <= 0`: unchanged."""
    if n <= 0:
        yield
        return
    from threadpoolctl import threadpool_limits

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
    from threadpoolctl import ThreadpoolController

    return [int(info["num_threads"]) for info in ThreadpoolController().select(user_api="blas").info()]


__all__ = ["OMP_WAIT_POLICY_DEFAULT", "apply_thread_policy", "blas_thread_counts", "blas_threads", "native_threads",
           "pool_threads", "torch_threads"]

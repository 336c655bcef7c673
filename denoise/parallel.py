"""The denoiser's CPU parallelism: one torch thread per task, tasks on Python threads.

Some of torch's CPU kernels split their sums by thread: oneDNN computes a convolution's weight gradient in
per-thread chunks and its forward pass with a blocking chosen for the thread count, and vectorised
element-wise functions take another path at each thread's chunk end. So a network trained or applied with
2 intra-op threads differs in its last bits from one trained with 1 (after 60 training steps the weights
differ by 3.6e-3), and a run's denoised photos would depend on the machine's or the Ray task's CPUs.

Here every torch operation of the denoiser runs with **one** intra-op thread, and the parallelism is
across independent pieces of fixed size: a training step's batch is split into a fixed number of chunks
(`N2VConfig.batch_chunks`) whose gradients are summed in chunk order; an image's inference passes run one
per task and are summed in pass order. The tasks run on up to `budget()` Python threads (torch releases
the GIL inside its kernels). The result depends on the chunk count only, never on the threads: with one
thread the chunks run one after the other and give the same bits. Measured on the 2-core reference
machine (width 16, batch 8 of 64 px, 20 steps): 2 chunks on 2 threads 0.85 s, the whole batch with 2
intra-op threads 0.79-1.07 s, with 1 thread 1.34-1.47 s; 8 inference passes over a 384x384 image on 2
threads 0.50-0.61 s against 0.90 s on one and 1.3-3.4 s with 2 intra-op threads.

`one_thread_per_task()` enters the mode: torch at one intra-op thread, and the budget the caller had
(its torch thread count: the machine's cores serially, the task's CPUs on Ray) remembered for the
nested calls, which would otherwise read 1.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar

import torch

from mvgeo.common.threads import torch_threads

__all__ = ["budget", "one_thread_per_task", "run_tasks"]

_BUDGET: ContextVar[int | None] = ContextVar("denoise_thread_budget", default=None)


def budget() -> int:
    """Python threads the denoiser's tasks may use: the budget of the enclosing `one_thread_per_task`, else
    torch's current intra-op thread count."""
    held = _BUDGET.get()
    return held if held is not None else max(1, torch.get_num_threads())


@contextmanager
def one_thread_per_task() -> Iterator[int]:
    """Run the block with one torch intra-op thread, keeping the caller's thread count as the `budget()` of
    `run_tasks` inside it (nested uses keep the outermost budget). Yields the budget."""
    held = budget()
    token = _BUDGET.set(held)
    try:
        with torch_threads(1):
            yield held
    finally:
        _BUDGET.reset(token)


def _one_thread() -> None:
    torch.set_num_threads(1)


def run_tasks[T, R](fn: Callable[[T], R], items: Iterable[T], *, device: torch.device | str = "cpu") -> list[R]:
    """``[fn(x) for x in items]``, on up to `budget()` Python threads with one torch thread each (CPU); in
    order, here, on other devices (whose kernels do not depend on CPU threads) or with a budget of 1.

    Each ``fn(x)`` must be independent of the others (no shared random generator, no shared output); the
    results come back in the order of `items`, so a caller that sums them in that order gets the same bits
    whatever the thread count.
    """
    work = list(items)
    with one_thread_per_task() as threads:
        workers = min(threads, len(work)) if torch.device(device).type == "cpu" else 1
        if workers <= 1:
            return [fn(x) for x in work]
        with ThreadPoolExecutor(max_workers=workers, initializer=_one_thread) as pool:
            return list(pool.map(fn, work))

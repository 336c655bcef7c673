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

__all__ = ["IN_FLIGHT_BYTES", "budget", "group_size", "in_parallel", "one_thread_per_task", "run_tasks"]

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


def _worker_start() -> None:
    """A worker thread: one torch thread, and a budget of 1, so that work nested in a task runs in order."""
    torch.set_num_threads(1)
    _BUDGET.set(1)


def run_tasks[T, R](fn: Callable[[T], R], items: Iterable[T], *, device: torch.device | str = "cpu") -> list[R]:
    """``[fn(x) for x in items]``, on up to `budget()` Python threads with one torch thread each (CPU); in
    order, here, on other devices (whose kernels do not depend on CPU threads) or with a budget of 1.

    Each ``fn(x)`` must be independent of the others (no shared random generator, no shared output); the
    results come back in the order of `items`, so a caller that sums them in that order gets the same bits
    whatever the thread count. The caller's grad mode holds in the workers too (torch keeps it per thread).
    """
    work = list(items)
    grad = torch.is_grad_enabled()

    def task(x: T) -> R:
        with torch.set_grad_enabled(grad):
            return fn(x)

    with one_thread_per_task() as threads:
        workers = min(threads, len(work)) if in_parallel(device) else 1
        if workers <= 1:
            return [fn(x) for x in work]
        with ThreadPoolExecutor(max_workers=workers, initializer=_worker_start) as pool:
            return list(pool.map(task, work))


def in_parallel(device: torch.device | str) -> bool:
    """Whether work on `device` is spread over threads: on CPU (other devices run it in order here)."""
    return torch.device(device).type == "cpu"


#: Bytes of full-image tensors (inputs and outputs) a group of inference passes may hold at once
#: (`group_size`); the networks' own activations, per tile, come on top, one set per thread.
IN_FLIGHT_BYTES = 256 * 2**20


def group_size(x: torch.Tensor) -> int:
    """How many passes over `x` (each an input and an output the size of `x`) to draw and run at once: the
    thread budget on CPU, at most what `IN_FLIGHT_BYTES` allows (at least 1); 1 on other devices. The
    results do not depend on it (passes are drawn in order and summed in order)."""
    if not in_parallel(x.device):
        return 1
    per_pass = 2 * x.numel() * x.element_size()
    return max(1, min(budget(), IN_FLIGHT_BYTES // max(per_pass, 1)))

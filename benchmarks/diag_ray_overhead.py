"""What a local Ray cluster costs before any work: start, the workers' first tasks (each worker process
starts and imports torch and the project), later tasks, shutdown. Usage: .venv/bin/python
benchmarks/diag_ray_overhead.py (prints one line of seconds)."""

import os
import time

t0 = time.perf_counter()
import eval.evaluate  # noqa: E402, F401  what a driver imports anyway
from eval.distributed import ClusterSettings, ray_cluster  # noqa: E402


def _pid(_item: int) -> int:
    return os.getpid()


def main() -> None:
    t1 = time.perf_counter()
    with ray_cluster(ClusterSettings(workers=2)) as executor:
        t2 = time.perf_counter()
        executor.run(_pid, [0, 1, 2, 3])
        t3 = time.perf_counter()
        pids = executor.run(_pid, [0, 1, 2, 3])
        t4 = time.perf_counter()
    t5 = time.perf_counter()
    print(f"imports {t1 - t0:.1f} s, cluster start {t2 - t1:.1f} s, first 4 tasks {t3 - t2:.1f} s, next 4 "
          f"{t4 - t3:.2f} s, shutdown {t5 - t4:.1f} s; worker processes {len(set(pids))}")


if __name__ == "__main__":
    main()

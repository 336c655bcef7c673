"""What a local Ray cluster costs before any work, with and without starting the workers as the cluster
starts (`ray_cluster(..., preload=...)`, as `denoise-gs eval` does): cluster start, the driver's own
preparation (the built-in scene rendered, as `denoise-gs eval llff_like --size 256x192` does first), the
first four tasks (each imports `eval.evaluate`, as a run does; without the preload the worker processes
start and import torch and the project only now), four more tasks, shutdown.

Usage: .venv/bin/python benchmarks/diag_ray_overhead.py [ROUNDS] (the two ways in turn, the first of each round
alternating; one line of seconds each)."""

import os
import sys
import tempfile
import time
from pathlib import Path

t0 = time.perf_counter()
import eval.evaluate  # noqa: E402  what a driver imports anyway
from eval.distributed import ClusterSettings, ray_cluster  # noqa: E402


def _pid(_item: int) -> int:
    import eval.evaluate  # noqa: F401  a run's own import

    return os.getpid()


def once(preload: tuple[str, ...]) -> str:
    t1 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, ray_cluster(ClusterSettings(workers=2), preload=preload) as executor:
        t2 = time.perf_counter()
        eval.evaluate.scene_dataset("builtin", "llff_like", Path(tmp), size_wh=(256, 192), views=12)
        t3 = time.perf_counter()
        executor.run(_pid, [0, 1, 2, 3])
        t4 = time.perf_counter()
        pids = executor.run(_pid, [0, 1, 2, 3])
        t5 = time.perf_counter()
    t6 = time.perf_counter()
    return (f"preload {list(preload) or 'none'}: cluster start {t2 - t1:.1f} s, driver's scene {t3 - t2:.1f} s, "
            f"first 4 tasks {t4 - t3:.1f} s, next 4 {t5 - t4:.2f} s, shutdown {t6 - t5:.1f} s, "
            f"all {t6 - t1:.1f} s; worker processes {len(set(pids))}")


def main() -> None:
    rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 1
    print(f"imports {time.perf_counter() - t0:.1f} s", flush=True)
    ways = [(), ("eval.evaluate",)]
    for r in range(rounds):
        for preload in ways if r % 2 == 0 else ways[::-1]:  # neither way always goes first
            print(once(preload), flush=True)


if __name__ == "__main__":
    main()

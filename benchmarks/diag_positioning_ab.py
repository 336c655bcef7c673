"""`mvgeo align` on the clean temple ring (the averaged start, whose global positioning runs the damped step)
with the global-positioning step of a base commit against this checkout's, alternating in one process:
seconds per run, the `global_align` stage (starts and alignment) and whether the poses differ.

Usage: .venv/bin/python benchmarks/diag_positioning_ab.py BASE_COMMIT [REPEATS]
(needs ../shared/data/temple_sparse_ring; the base's `_damped_step` is loaded from
`git show BASE_COMMIT:mvgeo/align/translation_averaging.py`).
"""

import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_real import OURS, prepare, temple_set

import mvgeo.align.translation_averaging as ta
from mvgeo.align.api import align_images
from mvgeo.common.imageio import list_images


def main(base: str, repeats: int) -> int:
    s = temple_set()
    if s is None:
        print("../shared/data/temple_sparse_ring is missing", file=sys.stderr)
        return 2
    work = Path(tempfile.mkdtemp())
    src = subprocess.run(["git", "show", f"{base}:mvgeo/align/translation_averaging.py"], check=True,
                         capture_output=True, text=True).stdout
    (work / "ta_base.py").write_text(src)
    spec = importlib.util.spec_from_file_location("ta_base", work / "ta_base.py")
    old = importlib.util.module_from_spec(spec)
    sys.modules["ta_base"] = old
    spec.loader.exec_module(old)

    def old_step(nq, lam, D, free):
        if not hasattr(nq.problem, "pairs"):  # the base kept its track pairs on the problem
            nq.problem.pairs = None
        return old._damped_step(nq, lam, D, free)

    steps = {"base": old_step, "this checkout": ta._damped_step}
    folder = prepare(s, work, False, 0)
    paths = [p for p in list_images(folder) if p.name in s.gt]
    runs: dict[str, list] = {k: [] for k in steps}
    for rep in range(repeats):
        for label in (list(steps) if rep % 2 == 0 else list(steps)[::-1]):
            ta._damped_step = steps[label]
            t = time.perf_counter()
            res = align_images(paths, OURS)
            runs[label].append((time.perf_counter() - t, res.stats.timings_s["global_align"],
                                res.sparse_model.cam_from_world_by_name()))
    ta._damped_step = steps["this checkout"]
    a, b = runs["base"][0][2], runs["this checkout"][0][2]
    for label, r in runs.items():
        print(f"{label}: median {np.median([x[0] for x in r]):.3f} s per run, global_align stage "
              f"{np.median([x[1] for x in r]):.3f} s ({repeats} runs)")
    print("largest pose difference:", max(float(np.abs(a[k] - b[k]).max()) for k in a))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 3))

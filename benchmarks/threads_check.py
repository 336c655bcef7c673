"""OpenMP wait policy check: N2V training steps with 1 thread, 2 threads (passive) and 2 threads (spinning).

Run each setting in its own process (the policy is read when torch's OpenMP runtime starts):
    for t in 1 2; do .venv/bin/python benchmarks/threads_check.py $t; done
    OMP_WAIT_POLICY=ACTIVE .venv/bin/python benchmarks/threads_check.py 2
`apply_thread_policy()` runs first, as in the command lines, so that OMP_WAIT_POLICY=PASSIVE is set
(unless the environment already sets it) before torch starts its thread pool. Not part of `make bench`: its
point only shows on a loaded machine, so report the load average with the figures.
"""

# isort: skip_file
# ruff: noqa: E402  (the thread policy must be applied before torch is imported)
from mvgeo.common.threads import apply_thread_policy

apply_thread_policy()  # first: before torch's OpenMP pool starts

import dataclasses
import os
import sys
import time

import numpy as np
import torch

from denoise.n2v import N2V_PRESETS, train_n2v

torch.set_num_threads(int(sys.argv[1]))
rng = np.random.default_rng(0)
imgs = [rng.random((120, 160, 3), dtype=np.float32) for _ in range(4)]
cfg = dataclasses.replace(N2V_PRESETS["fast"], steps=30)
t = time.perf_counter()
train_n2v(imgs, cfg, seed=0)
print(f"{sys.argv[1]} threads, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}: "
      f"{time.perf_counter() - t:.2f} s for 30 N2V steps")

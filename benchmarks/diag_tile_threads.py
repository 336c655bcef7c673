"""One large photo through a one-pass network (Neighbor2Neighbor's inference): its tiles on 1 and 2 threads.

`denoise.inference.predict_tiled` cuts a photo larger than one tile (512 px cores, 48 px of context) into
tiles fixed by the tile size, and runs them one per task on the caller's thread budget
(`denoise.parallel`): the same bits on any thread count. A photo alone (a one-pass method, or `passes=0`)
has no other work to spread. Prints, per network preset, the seconds of `denoise_one_pass` on one
1600x1200 photo (PHOTO resized, sigma 25/255 added) with 1 and 2 caller threads, alternating, and whether
the outputs are identical. The networks are untrained (the time does not depend on the weights).

Usage: OMP_WAIT_POLICY=PASSIVE python benchmarks/diag_tile_threads.py PHOTO [REPEATS]
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from denoise.n2v import N2V_PRESETS, new_model
from denoise.self_supervised import denoise_one_pass
from mvgeo.common.deps import cv2
from mvgeo.common.imageio import read_image


def main(argv: list[str]) -> int:
    photo = read_image(argv[0])
    repeats = int(argv[1]) if len(argv) > 1 else 2
    img = cv2.resize(photo, (1600, 1200), interpolation=cv2.INTER_CUBIC)
    img = np.clip(img + np.random.default_rng(0).normal(0, 25 / 255, img.shape), 0, 1).astype(np.float32)
    print("| network | 1 thread (s) | 2 threads (s) | ratio | identical |\n|---|---|---|---|---|")
    for preset in ("default", "wide"):
        model = new_model(N2V_PRESETS[preset], [torch.rand(3, 32, 32)], seed=0)
        model.blind_spot = False
        times: dict[int, list[float]] = {1: [], 2: []}
        outs = {}
        for _ in range(repeats):
            for threads in (1, 2):
                torch.set_num_threads(threads)
                t = time.perf_counter()
                outs[threads] = denoise_one_pass(model, [img])[0]
                times[threads].append(time.perf_counter() - t)
        one, two = float(np.median(times[1])), float(np.median(times[2]))
        print(f"| `{preset}` | {one:.2f} | {two:.2f} | {one / two:.2f}x | {np.array_equal(outs[1], outs[2])} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

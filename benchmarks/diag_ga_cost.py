"""What the DUSt3R global alignment's time is made of: its iterations against its pixel stride.

`mvgeo align` as `benchmarks/bench_real.py` runs it (`ours`) on DTU scan24 (cluster) with sigma 25/255
added (noise seed 0); the first global alignment's inputs (pair predictions, sizes, start) are kept and
`global_align` runs again on them with the given `pixel_stride x iters` settings, each `--repeats` times
in alternating order. Prints the pointmap size and the number of pairs, and per setting the median and
least seconds.

Run: `OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/diag_ga_cost.py [--configs=4x100,8x100,4x50,4x0]
[--repeats=5]` (needs ../shared/data).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import cli_option, md_table, recorded_calls
from bench_real import OURS, dtu_for_script, exif_focal_35mm_of, prepare

import mvgeo.align.solve as solve
from mvgeo.align.api import align_images
from mvgeo.common.imageio import list_images, read_image


def main() -> int:
    s = dtu_for_script(__doc__)
    if s is None:
        return 0
    configs = [tuple(int(v) for v in c.split("x")) for c in cli_option("configs", "4x100,8x100,4x50,4x0").split(",")]
    repeats = int(cli_option("repeats", "5"))
    with tempfile.TemporaryDirectory(prefix="diag-ga-") as tmp, recorded_calls(solve, "global_align") as calls:
        wh = read_image(s.files[0]).shape[1::-1]
        folder = prepare(s, Path(tmp), True, 0, exif_focal_35mm_of(s.K, wh))
        align_images([p for p in list_images(folder) if p.name in s.gt], OURS)
    (preds, sizes), kwargs = calls[0][0][:2], calls[0][1]
    base = kwargs["config"]
    times = {c: [] for c in configs}
    for rep in range(repeats):
        for c in (configs if rep % 2 == 0 else configs[::-1]):
            cfg = replace(base, pixel_stride=c[0], iters=c[1])
            t = time.perf_counter()
            solve.global_align(preds, sizes, **dict(kwargs, config=cfg))
            times[c].append(time.perf_counter() - t)
    h, w = sizes[0]
    print(f"{len(preds)} pairs, pointmaps {w}x{h}: at pixel stride k each pair's two pointmaps sample about "
          f"2 x ({h}/k) x ({w}/k) pixels")
    print(md_table(["pixel stride x iterations", "median s", "min s"],
                   [[f"{c[0]}x{c[1]}", f"{np.median(v):.3f}", f"{min(v):.3f}"] for c, v in times.items()]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The global alignment's pixel stride and iterations against the poses, through whole alignments.

`mvgeo align` as `benchmarks/bench_real.py` runs it (`ours`: dense stereo off, the EXIF focal a camera would
write) on the temple ring (clean) and DTU scan24 (cluster) clean and with sigma 25/255 added (noise seeds
0-2); each `GlobalAlignConfig` setting `pixel_stride x iters` on the same images, in alternating order per
set. Prints per run the registered views, rotation error median / max (deg, over all pairs of views), ATE /
scene scale, the seconds and the global-alignment stage's seconds, then the means per setting. For the
stage's own time without the rest of the alignment: `benchmarks/diag_ga_cost.py`.

Run: `OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/diag_align_stride.py [--configs=4x100,6x100,8x100]`
(needs ../shared/data).
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import cli_option, md_table
from bench_real import OURS, dtu_set, exif_focal_35mm_of, metrics_row, prepare, temple_set

from mvgeo.align.api import align_images
from mvgeo.common.imageio import list_images, read_image


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    configs = [tuple(int(v) for v in c.split("x")) for c in cli_option("configs", "4x100,6x100,8x100").split(",")]
    sets = [s for s in (temple_set(), dtu_set("cluster")) if s is not None]
    if not sets:
        print("../shared/data is missing: nothing to run")
        return 0
    rows, per = [], {c: [] for c in configs}
    with tempfile.TemporaryDirectory(prefix="diag-stride-") as tmp:
        k = 0
        for s in sets:
            wh = read_image(s.files[0]).shape[1::-1]
            f35 = exif_focal_35mm_of(s.K, wh)
            draws = [("clean", False, 0)]
            if s.add_noise and s.name.startswith("dtu"):
                draws += [(f"sigma 25 (seed {seed})", True, seed) for seed in range(3)]
            for label, noisy, seed in draws:
                folder = prepare(s, Path(tmp) / str(k), noisy, seed, f35)
                paths = [p for p in list_images(folder) if p.name in s.gt]
                name = f"{s.name}, {label}"
                for c in (configs if k % 2 == 0 else configs[::-1]):
                    cfg = replace(OURS, align=replace(OURS.align, pixel_stride=c[0], iters=c[1]))
                    t = time.perf_counter()
                    try:
                        res = align_images(paths, cfg)
                    except Exception as exc:  # report, keep going
                        rows.append([name, f"{c[0]}x{c[1]}", f"failed: {type(exc).__name__}", "", "", "",
                                     f"{time.perf_counter() - t:.2f}", ""])
                        continue
                    sec = time.perf_counter() - t
                    r = metrics_row(name, "", res.sparse_model.cam_from_world_by_name(), s.gt, 1.0, 1.0, sec)
                    ga = res.stats.timings_s.get("global_align", float("nan"))
                    rows.append([name, f"{c[0]}x{c[1]}", r[2], f"{r[3]:.3f}", f"{r[4]:.3f}", f"{r[6]:.4f}",
                                 f"{sec:.2f}", f"{ga:.2f}"])
                    per[c].append((r[3], r[4], r[6], sec, ga))
                    print(" | ".join(map(str, rows[-1])), flush=True)
                k += 1
    print(md_table(["set", "stride x iters", "registered", "rot med", "rot max", "ATE / scale", "s",
                    "global_align s"], rows))
    print(md_table(["stride x iters", "runs", "rot med mean", "rot max mean", "ATE mean", "s mean",
                    "global_align s mean"],
                   [[f"{c[0]}x{c[1]}", len(v)] + [f"{np.mean([x[i] for x in v]):.4f}" for i in range(5)]
                    for c, v in per.items() if v]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The alignment's pair refinement, re-adjustment and re-estimation count, over several draws of the noise.

`mvgeo align` (dense stereo off, no intrinsics) on the 12 DTU scan24 `cluster` views of `bench_real.py` with
Gaussian noise sigma 25/255 added, once per noise seed, in four configurations run one after the other on
each draw:

- `before`: USAC's relative poses as they come (`TwoViewConfig.refine` off), one bundle adjustment
  (`BundleConfig.readjust_min_gain` 0), at most two focal re-estimations (`policy.MAX_REFOCUS` = 2);
- `readjust`: the same with the re-adjustment;
- `refine, 2 re-estimations`: refined pairs and the re-adjustment, two re-estimations;
- `now`: the defaults (refined pairs, re-adjustment, three re-estimations).

Prints one row per draw and configuration, then per configuration the mean over the draws of the median and
of the max relative rotation error (deg, `mvgeo.metrics.compare_poses`), the worst draw, and the mean time.

Run: `.venv/bin/python benchmarks/diag_align_defaults.py [--seeds=0,1,2,3,4,5]` (needs ../shared/data).
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import cli_option, md_table
from bench_real import OURS, dtu_for_script, prepare

from mvgeo.align import policy
from mvgeo.align.api import align_images
from mvgeo.metrics import compare_poses


def configurations():
    raw = replace(OURS.pairwise, two_view=replace(OURS.pairwise.two_view, refine=False))
    once = replace(OURS.bundle, readjust_min_gain=0.0)
    return [("before", replace(OURS, pairwise=raw, bundle=once), 2),
            ("readjust", replace(OURS, pairwise=raw), 2),
            ("refine, 2 re-estimations", OURS, 2),
            ("now", OURS, policy.MAX_REFOCUS)]


def main() -> int:
    s = dtu_for_script(__doc__)
    if s is None:
        return 0
    seeds = [int(x) for x in cli_option("seeds", "0,1,2,3,4,5").split(",")]
    default_refocus = policy.MAX_REFOCUS
    rows, per = [], {}
    with tempfile.TemporaryDirectory(prefix="diag-align-") as tmp:
        for seed in seeds:
            folder = prepare(s, Path(tmp) / str(seed), True, seed)
            files = sorted(folder.glob("*.png"))
            for name, cfg, refocus in configurations():
                policy.MAX_REFOCUS = refocus
                t = time.perf_counter()
                try:
                    res = align_images(files, cfg)
                    m = compare_poses(res.sparse_model.cam_from_world_by_name(), s.gt)
                    row = [seed, name, f"{m.n_registered}/{m.n_ref}", float(np.median(m.rotation_deg)),
                           float(np.max(m.rotation_deg)), time.perf_counter() - t]
                except Exception as exc:  # report, keep going
                    row = [seed, name, f"failed: {type(exc).__name__}", float("nan"), float("nan"),
                           time.perf_counter() - t]
                finally:
                    policy.MAX_REFOCUS = default_refocus
                rows.append(row)
                per.setdefault(name, []).append(row)
                print(row, file=sys.stderr, flush=True)
    print(md_table(["noise seed", "configuration", "registered", "rot med (deg)", "rot max (deg)", "time (s)"], rows))
    summary = []
    for name, rs in per.items():
        med, mx = np.array([r[3] for r in rs]), np.array([r[4] for r in rs])
        worst = int(np.nanargmax(med)) if np.isfinite(med).any() else 0
        summary.append([name, float(np.nanmean(med)), float(np.nanmean(mx)),
                        f"seed {rs[worst][0]}: {med[worst]:.3g} / {mx[worst]:.3g}",
                        float(np.mean([r[5] for r in rs]))])
    print()
    print(md_table(["configuration", "rot med: mean (deg)", "rot max: mean (deg)", "worst draw (med / max)",
                    "time: mean (s)"], summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The two-view refinement (`mvgeo.twoview._refine`) of a base commit against this checkout's, on the calls
`mvgeo align` makes on real photos: seconds for all of them, alternating, and how far apart the two
solutions are.

Usage: .venv/bin/python benchmarks/diag_twoview_refine.py BASE_COMMIT [REPEATS]
(needs ../shared/data/dtu_scan24; the base's module is loaded from `git show BASE_COMMIT:mvgeo/twoview.py`).

The calls are recorded while `mvgeo align` (poses only, EXIF focal, `bench_real.py`'s `ours`) aligns DTU
scan24's 12 clustered training views, clean and with Gaussian noise sigma 25/255 (seed 0): every pair's
calibrated refinement on its inliers, each re-selection of the inliers included. Each version then refines
the same inputs, the two alternating REPEATS times (default 5); the table gives the fastest run of each.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import recorded_calls
from bench_real import OURS, dtu_set, exif_focal_35mm_of, prepare

import mvgeo.twoview as tv
from mvgeo.align.api import align_images
from mvgeo.common.imageio import list_images
from mvgeo.metrics import rotation_error_deg, translation_direction_error_deg


def _record_calls(noisy: bool, work: Path) -> list[tuple]:
    s = dtu_set("cluster")
    folder = prepare(s, work, noisy=noisy, seed=0, exif_35mm=exif_focal_35mm_of(s.K, (384, 384)))
    paths = [p for p in list_images(folder) if p.name in s.gt]
    with recorded_calls(tv, "_refine") as calls:
        align_images(paths, OURS)
    return calls


def _base_module(base: str):
    src = subprocess.run(["git", "show", f"{base}:mvgeo/twoview.py"], check=True, capture_output=True, text=True)
    path = Path(tempfile.mkdtemp()) / "twoview_base.py"
    path.write_text(src.stdout)
    spec = importlib.util.spec_from_file_location("twoview_base", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["twoview_base"] = mod
    spec.loader.exec_module(mod)
    return mod


def main(base: str, repeats: int) -> int:
    if dtu_set("cluster") is None:
        print("../shared/data/dtu_scan24 is missing", file=sys.stderr)
        return 2
    old = _base_module(base)
    work = Path(tempfile.mkdtemp())
    print(f"| photos | refinements | base {base[:7]} (s) | this (s) | speed-up | largest rotation / translation "
          "difference (deg) |\n|---|---|---|---|---|---|")
    for noisy in (False, True):
        calls = _record_calls(noisy, work)
        best = {"base": np.inf, "this": np.inf}
        out = {}
        for _ in range(repeats):
            for name, fn in (("base", old._refine), ("this", tv._refine)):
                t = time.perf_counter()
                out[name] = [fn(*a, **k) for a, k in calls]
                best[name] = min(best[name], time.perf_counter() - t)
        dr = max(rotation_error_deg(a[0], b[0]) for a, b in zip(out["base"], out["this"], strict=True))
        dt = max(translation_direction_error_deg(a[1], b[1]) for a, b in zip(out["base"], out["this"], strict=True))
        print(f"| DTU scan24 (cluster), {'sigma 25' if noisy else 'clean'} | {len(calls)} | {best['base']:.3f} | "
              f"{best['this']:.3f} | {best['base'] / best['this']:.2f}x | {dr:.2g} / {dt:.2g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 5))

"""The bundle adjustment (`mvgeo.align.bundle.bundle_adjust`: the tracks' triangulation and the LM solver) of
a base commit against this checkout's, on the calls `mvgeo align` makes on real photos: seconds for all of
them, alternating, and how far apart the results are.

Usage: .venv/bin/python benchmarks/diag_bundle_speed.py BASE_COMMIT [REPEATS]
(needs ../shared/data; the base is a temporary `git worktree` of BASE_COMMIT).

The calls are recorded while `mvgeo align` (poses only, EXIF focal, `bench_real.py`'s `ours`) aligns the
temple ring's 12 views (clean) and DTU scan24's 12 clustered training views, clean and with Gaussian noise
sigma 25/255 (seed 0): every bundle adjustment of every candidate, the principal point's included. Each
version then replays the same calls in its own process (one BLAS thread, as the alignment's later stages
run), the two alternating REPEATS times (default 3); the table gives the fastest run of each.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
from _common import ROOT, base_worktree, recorded_calls
from bench_real import OURS, dtu_set, exif_focal_35mm_of, prepare, temple_set

import mvgeo.align.solve as solve_mod
from mvgeo.align.api import align_images
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import rotation_error_deg

_REPLAY = """
import pickle, sys, time
sys.path.insert(0, sys.argv[1])
from mvgeo.align.bundle import bundle_adjust
calls = pickle.load(open(sys.argv[2], "rb"))
t = time.perf_counter()
out = [bundle_adjust(*a, **k) for a, k in calls]
sec = time.perf_counter() - t
pickle.dump((sec, [(r.cam_from_world, r.focal_px, r.n_points) for r in out]), open(sys.argv[3], "wb"))
"""


def _record_calls(s, noisy: bool, work: Path) -> list[tuple]:
    wh = read_image(s.files[0]).shape[1::-1]
    folder = prepare(s, work, noisy=noisy, seed=0, exif_35mm=exif_focal_35mm_of(s.K, wh))
    with recorded_calls(solve_mod, "bundle_adjust") as calls:
        align_images([p for p in list_images(folder) if p.name in s.gt], OURS)
    return calls


def _replay(src: Path, calls_file: Path, out_file: Path) -> tuple[float, list]:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               OMP_WAIT_POLICY="PASSIVE")
    subprocess.run([sys.executable, "-c", _REPLAY, str(src), str(calls_file), str(out_file)], check=True, env=env,
                   cwd=src)
    return pickle.loads(out_file.read_bytes())


def main(base: str, repeats: int) -> int:
    sets = [("temple ring, clean", temple_set(), False), ("DTU scan24 (cluster), clean", dtu_set("cluster"), False),
            ("DTU scan24 (cluster), sigma 25", dtu_set("cluster"), True)]
    sets = [x for x in sets if x[1] is not None]
    if not sets:
        print("../shared/data holds neither set", file=sys.stderr)
        return 2
    with base_worktree(base, prefix="diag-bundle-") as base_src:
        _compare(sets, base, base_src, base_src.parent, repeats)
    return 0


def _compare(sets, base: str, base_src: Path, work: Path, repeats: int) -> None:
    print(f"| photos | adjustments | base {base[:7]} (s) | this (s) | speed-up | largest rotation difference (deg) "
          "| largest focal difference (relative) | tracks |\n|---|---|---|---|---|---|---|---|")
    for label, s, noisy in sets:
        calls = _record_calls(s, noisy, work)
        calls_file = work / "calls.pkl"
        calls_file.write_bytes(pickle.dumps(calls))
        best = {"base": np.inf, "this": np.inf}
        out = {}
        for _ in range(repeats):
            for name, src in (("base", base_src), ("this", ROOT)):
                sec, out[name] = _replay(src, calls_file, work / f"{name}.pkl")
                best[name] = min(best[name], sec)
        pairs = list(zip(out["base"], out["this"], strict=True))
        dr = max(rotation_error_deg(a[0][v, :, :3], b[0][v, :, :3]) for a, b in pairs for v in range(len(a[0])))
        df = max(float(np.max(np.abs(a[1] / b[1] - 1.0))) for a, b in pairs)
        same_tracks = all(a[2] == b[2] for a, b in pairs)
        print(f"| {label} | {len(calls)} | {best['base']:.3f} | {best['this']:.3f} | "
              f"{best['base'] / best['this']:.2f}x | {dr:.2g} | {df:.2g} | "
              f"{'the same' if same_tracks else 'differ'} |")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 3))

"""Calibrated two-view poses on (nearly) planar scenes: right, wrong (the plane's other pose) or refused.

On a plane two relative poses explain the matches to the noise (the homography's two decompositions);
`mvgeo.twoview.estimate_relative_pose` takes the one putting more points in front of both cameras where a
homography is the better model (GRIC), and fails naming the ambiguity where the two cannot be told apart.
This counts, over seeded scenes, how often a success is right (within 4 deg; the plane's other pose is 6-12
deg away here), wrong, or a failure: points on the plane z = 6 + 0.3 x (4 x 4 units, 6 units away), relief
added uniformly in +-RELIEF, camera 2 about 1 unit to the side and turned about 6 deg, f = 520 px at 640 x 480,
300 matches of which 20 % are random, Gaussian noise per pixel coordinate.

Usage: .venv/bin/python benchmarks/diag_planar_twoview.py [--seeds 40] [--src DIR ...]
(each `--src` is another checkout whose `mvgeo` is measured the same way, e.g. a worktree of an earlier commit)
"""
import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

RELIEFS = (0.0, 0.02, 0.05, 0.1, 0.3)
NOISES_PX = (0.3, 1.0)
W, H = 640, 480


def _scene(rng, relief: float, noise_px: float, n: int = 300, outliers: float = 0.2, f: float = 520.0):
    from mvgeo import transforms as tf

    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    X = rng.uniform(-2, 2, (n, 3)) + [0, 0, 6]
    X[:, 2] = 6 + 0.3 * X[:, 0] + relief * rng.uniform(-1, 1, n)
    R = tf.so3_exp(rng.normal(scale=0.1, size=3))
    t = np.array([-1.0, 0.1, 0.2]) + rng.normal(scale=0.2, size=3)
    t /= np.linalg.norm(t)

    def project(Y):
        u = Y @ K.T
        return u[:, :2] / u[:, 2:]

    u1 = project(X) + rng.normal(scale=noise_px, size=(n, 2))
    u2 = project(X @ R.T + t) + rng.normal(scale=noise_px, size=(n, 2))
    out = rng.random(n) < outliers
    u2[out] = rng.uniform([0, 0], [W, H], (out.sum(), 2))
    return K, R, u1, u2


def measure(seeds: int) -> dict[str, dict[str, int]]:
    from mvgeo.metrics import rotation_error_deg
    from mvgeo.twoview import estimate_relative_pose

    counts = {}
    for relief in RELIEFS:
        for noise in NOISES_PX:
            c = {"right": 0, "wrong": 0, "refused": 0}
            for seed in range(seeds):
                K, R, u1, u2 = _scene(np.random.default_rng(seed), relief, noise)
                res = estimate_relative_pose(u1, u2, K, K)
                c["refused" if not res.success else "right" if rotation_error_deg(res.R, R) < 4.0 else "wrong"] += 1
            counts[f"{relief}/{noise}"] = c
    return counts


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--src", type=Path, action="append", default=[], help="another checkout to measure")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # one checkout's counts, for --src
    args = ap.parse_args()
    if args.json:
        print(json.dumps(measure(args.seeds)))
        return 0
    columns = {"this checkout": measure(args.seeds)}
    for src in args.src:
        env = {**os.environ, "PYTHONPATH": str(src.resolve())}
        done = subprocess.run([sys.executable, __file__, "--json", "--seeds", str(args.seeds)], env=env,
                              cwd=src, capture_output=True, text=True, check=True)
        columns[str(src)] = json.loads(done.stdout.strip().splitlines()[-1])
    print(f"{args.seeds} scenes per row; right / wrong (success, >= 4 deg off) / refused\n")
    print("| relief | noise (px) | " + " | ".join(columns) + " |")
    print("|---|---|" + "---|" * len(columns))
    for relief in RELIEFS:
        for noise in NOISES_PX:
            cells = [" / ".join(str(c[f"{relief}/{noise}"][k]) for k in ("right", "wrong", "refused"))
                     for c in columns.values()]
            print(f"| {relief} | {noise} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

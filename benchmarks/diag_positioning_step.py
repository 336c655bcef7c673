"""One LM step of global positioning (`mvgeo.align.translation_averaging`): the block solve `_damped_step`
against the scipy.sparse reference `_damped_step_sparse`, on random problems from 12 views x 2000 tracks to
100 views x 30000 tracks (2-5 observations per track, rays 0.01 rad from the truth), seconds per step and
the largest difference relative to the step.

Usage: .venv/bin/python benchmarks/diag_positioning_step.py (one line per size: first block step (with the
normal equations); a second block step; one sparse step; difference)."""

import time

import numpy as np

from mvgeo.align.translation_averaging import _damped_step, _damped_step_sparse, _Normal, _Problem


def main() -> None:
    rng = np.random.default_rng(0)
    for n, P in [(12, 2000), (24, 5000), (50, 20000), (100, 30000)]:
        m = rng.integers(2, 6, P)
        op = np.repeat(np.arange(P), m)
        ov = np.concatenate([rng.choice(n, k, replace=False) for k in m])
        C, X = rng.normal(size=(n, 3)), rng.normal(size=(P, 3)) * 3
        w = X[op] - C[ov]
        v = w / np.linalg.norm(w, axis=1, keepdims=True) + rng.normal(size=w.shape) * 0.01
        pb = _Problem(v, ov, op, n, P)
        z = np.r_[C.ravel(), X.ravel(), 1 / np.linalg.norm(w, axis=1)]
        wt, free = np.ones(len(op)), np.ones(len(op), bool)
        t = time.perf_counter()
        nq = _Normal(pb, z, wt)
        D = np.clip(nq.diagonal(), 1e-12, 1e32)
        _damped_step(nq, 1e-3, D, free)
        first = time.perf_counter() - t
        t = time.perf_counter()
        block = _damped_step(nq, 1e-3, D, free)
        again = time.perf_counter() - t
        t = time.perf_counter()
        sparse = _damped_step_sparse(pb, z, wt, 1e-3, free)
        ts = time.perf_counter() - t
        diff = float(np.abs(block - sparse).max() / np.abs(sparse).max())
        print(f"{n} views x {P} tracks ({len(op)} observations): block {first:.3f} s (first), {again:.3f} s; "
              f"sparse {ts:.3f} s; relative difference {diff:.1e}", flush=True)


if __name__ == "__main__":
    main()

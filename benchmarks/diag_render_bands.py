"""How a run's round-1 renders and its denoised photos compare with the clean photos, band by band, at the
training views: the measurement behind a round 2 that takes detail from the renders (the paper's round-2
loss keeps the denoiser's low frequencies and takes the detail from the first splat's renders).

Bands are differences of Gaussian blurs (sigma 0 = the image itself, then 1, 2, 4, 8, 16 px, the last band
everything coarser). Per band: the mean squared error of the render and of the denoised photo against the
clean photo, and the blend ``denoised + a (render - denoised)`` with each photo's best `a` (an oracle: it
needs the clean photo), with the median of those `a`. The render and the denoised photo are the run's
`round1/renders/` and `round1/denoised/`; the clean photos are the dataset's `clean/`.

Usage: .venv/bin/python benchmarks/diag_render_bands.py DATASET RUN_DIR [DATASET RUN_DIR ...]
(RUN_DIR: an evaluation's `runs/SCENE/seedK/METHOD`, holding `round1/renders/` and `round1/denoised/`)
"""
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from eval.pipeline.views import read_views

SIGMAS_PX = (0, 1, 2, 4, 8, 16)


def _blur(x: np.ndarray, s: float) -> np.ndarray:
    return x if s == 0 else gaussian_filter(x, (s, s, 0))


def bands(x: np.ndarray) -> list[np.ndarray]:
    """Band k: blur(SIGMAS_PX[k]) - blur(SIGMAS_PX[k + 1]); the last: blur(SIGMAS_PX[-1])."""
    blurred = [_blur(x, s) for s in SIGMAS_PX]
    return [blurred[k] - blurred[k + 1] for k in range(len(SIGMAS_PX) - 1)] + [blurred[-1]]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a - b) ** 2)))


def main() -> int:
    args = sys.argv[1:]
    if not args or len(args) % 2:
        raise SystemExit(__doc__)
    for dataset, run in zip(args[::2], args[1::2], strict=True):
        run = Path(run)
        renders = read_views(run / "round1" / "renders")
        stems = list(renders)
        denoised = read_views(run / "round1" / "denoised", stems)
        clean = read_views(Path(dataset) / "clean", stems)
        rows = np.zeros((len(SIGMAS_PX), 3))
        best_a: list[list[float]] = [[] for _ in SIGMAS_PX]
        for k in stems:
            c, r, d = (bands(x[k].astype(np.float64)) for x in (clean, renders, denoised))
            for b in range(len(SIGMAS_PX)):
                u, v = r[b] - d[b], c[b] - d[b]
                a = float(np.clip(np.sum(u * v) / max(np.sum(u * u), 1e-12), 0.0, 1.0))
                rows[b] += [np.mean((r[b] - c[b]) ** 2), np.mean(v * v), np.mean((d[b] + a * u - c[b]) ** 2)]
                best_a[b].append(a)
        rows /= len(stems)
        print(f"\n{run} ({len(stems)} views): PSNR against the clean photos, render "
              f"{np.mean([psnr(renders[k], clean[k]) for k in stems]):.2f} dB, denoised "
              f"{np.mean([psnr(denoised[k], clean[k]) for k in stems]):.2f} dB\n")
        print("| band (px) | render MSE x 1e4 | denoised MSE x 1e4 | best blend MSE x 1e4 | best a, median (range) |")
        print("|---|---|---|---|---|")
        for b, s in enumerate(SIGMAS_PX):
            hi = f"{SIGMAS_PX[b + 1]}" if b + 1 < len(SIGMAS_PX) else "inf"
            print(f"| {s}-{hi} | {rows[b, 0] * 1e4:.3f} | {rows[b, 1] * 1e4:.3f} | {rows[b, 2] * 1e4:.3f} | "
                  f"{np.median(best_a[b]):.2f} ({min(best_a[b]):.2f}-{max(best_a[b]):.2f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

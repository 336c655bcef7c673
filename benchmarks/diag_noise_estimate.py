"""The noise std the denoisers read from each photo: the unclipped patches' PCA estimate against the clipped-noise
fit (`denoise.noise_level`), and an evaluation run with the previous estimator for a before/after.

Usage:
  .venv/bin/python benchmarks/diag_noise_estimate.py photos DIR [DIR...]
      per folder: the range of `fit_clipped_noise_sigma`, of `estimate_noise_sigma_pca(exclude_clipped=True)`
      and of `estimate_noise_sigma_clipped` (the larger; what the denoisers use) over its PNG photos (/255), and
      how many photos the larger changes;
  .venv/bin/python benchmarks/diag_noise_estimate.py cost DIR [REPEATS]
      the seconds of `denoise.self_supervised.r2r_noise_std` (what the denoise stage estimates once per photo)
      per PNG photo of DIR: median over the photos of each photo's fastest of REPEATS (default 3) calls;
  .venv/bin/python benchmarks/diag_noise_estimate.py eval-unclipped DATASET --out OUT [denoise-gs eval options]
      `denoise-gs eval` with `denoise.self_supervised.estimate_noise_sigma_clipped` replaced by the unclipped
      patches' estimate (the estimator before the clipped-noise fit), everything else as this checkout.
"""

import sys
from pathlib import Path

from eval.cli import main as eval_main  # first: sets the thread policy before torch loads


def photos(folders: list[str]) -> int:
    from denoise.noise_level import estimate_noise_sigma_clipped, estimate_noise_sigma_pca, fit_clipped_noise_sigma
    from mvgeo.common.imageio import read_image

    for d in folders:
        files = sorted(Path(d).glob("*.png"))
        if not files:
            print(f"{d}: no PNG photos", file=sys.stderr)
            return 2
        fit, old, new = [], [], []
        for p in files:
            img = read_image(p)
            fit.append(255 * fit_clipped_noise_sigma(img))
            old.append(255 * estimate_noise_sigma_pca(img, exclude_clipped=True))
            new.append(255 * estimate_noise_sigma_clipped(img))
        changed = sum(a != b for a, b in zip(old, new, strict=True))
        print(f"{d} ({len(files)} photos): fit {min(fit):.1f}-{max(fit):.1f}, unclipped {min(old):.1f}-{max(old):.1f}"
              f" -> used {min(new):.1f}-{max(new):.1f} (/255); {changed} changed")
    return 0


def cost(args: list[str]) -> int:
    import time

    import numpy as np

    from denoise.self_supervised import r2r_noise_std
    from mvgeo.common.imageio import read_image

    files = sorted(Path(args[0]).glob("*.png"))
    if not files:
        print(f"{args[0]}: no PNG photos", file=sys.stderr)
        return 2
    repeats = int(args[1]) if len(args) > 1 else 3
    per_photo = []
    for p in files:
        img = read_image(p)
        best = float("inf")
        for _ in range(repeats):
            t = time.perf_counter()
            r2r_noise_std(img)
            best = min(best, time.perf_counter() - t)
        per_photo.append(best)
    h, w = read_image(files[0]).shape[:2]
    print(f"{args[0]} ({len(files)} photos, {w}x{h}): r2r_noise_std {np.median(per_photo):.3f} s per photo "
          f"(range {min(per_photo):.3f}-{max(per_photo):.3f})")
    return 0


def eval_unclipped(args: list[str]) -> int:
    import denoise.self_supervised as ss
    from denoise.noise_level import estimate_noise_sigma_pca

    ss.estimate_noise_sigma_clipped = lambda img: estimate_noise_sigma_pca(img, exclude_clipped=True)
    return eval_main(["eval", *args])


if __name__ == "__main__":
    modes = {"photos": photos, "cost": cost, "eval-unclipped": eval_unclipped}
    if len(sys.argv) < 3 or sys.argv[1] not in modes:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    sys.exit(modes[sys.argv[1]](sys.argv[2:]))

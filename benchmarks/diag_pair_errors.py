"""Which pairs of views hold `mvgeo align`'s largest relative rotation errors on real photos.

For each set named as `diag_verdict_perturbed.set_images` names them (e.g. `dtu_noisy:1`: DTU scan24 cluster at
sigma 25/255, noise seed 1), the images tagged with the calibration's EXIF focal (as `bench_real.py --exif`),
aligned with `bench_real.OURS`; prints the median and the five largest relative rotation errors against the
calibration (`mvgeo.metrics.relative_pose_errors`), with their pairs, and each view's mean error over its pairs.

Usage: .venv/bin/python benchmarks/diag_pair_errors.py SET [SET ...]      (e.g. dtu_noisy:1 dtu_noisy:2)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2  # noqa: F401  before pycolmap (a PNG write after the reverse order aborts)
import numpy as np
from bench_real import OURS, exif_focal_35mm_of
from diag_verdict_perturbed import _variant, set_images

from mvgeo.align.api import align_images
from mvgeo.common.imageio import read_image
from mvgeo.metrics import relative_pose_errors


def main() -> int:
    for name in sys.argv[1:] or ["dtu_noisy:1", "dtu_noisy:2"]:
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            paths, gt, K = set_images(name, work)
            h, w = read_image(paths[0]).shape[:2]
            tagged = _variant(paths, work / "exif", exif_focal_35mm_of(K, (w, h)), "none")
            model = align_images(tagged, OURS).sparse_model
            names = [p.name for p in tagged]
            rel = relative_pose_errors(np.stack([model.image(n).cam_from_world for n in names]),
                                       np.stack([gt[n] for n in names]))
            worst = np.argsort(rel.rotation_deg)[::-1][:5]
            print(f"{name}: rotation error median {np.median(rel.rotation_deg):.3f} deg; largest: " +
                  ", ".join(f"{names[i]}-{names[j]} {rel.rotation_deg[k]:.2f}"
                            for k, (i, j) in ((k, rel.pairs[k]) for k in worst)))
            per_view = [np.mean(rel.rotation_deg[(rel.pairs == v).any(axis=1)]) for v in range(len(names))]
            print("  mean over each view's pairs: " + ", ".join(f"{n} {e:.2f}" for n, e in zip(names, per_view,
                                                                                            strict=True)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

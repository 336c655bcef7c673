"""Raw DTU scan24 photos at sigma 50/255: is the match graph the gap to pycolmap, would a blur before SIFT
relate more views, and does a camera model with radial distortion matter on DTU?

Usage: .venv/bin/python benchmarks/diag_front_end_s50.py [--seeds=0,1] [--blur=0,1.0,1.7] [--blur-seeds=0,1,2,3]
[--models=SIMPLE_RADIAL,SIMPLE_PINHOLE] [--model-sets=dtu,dtu_noisy]

Prints three tables (nothing written):
- pycolmap's verified pairs (extraction and exhaustive matching, `bench_real.colmap_verified_pairs`: 15 inliers
  or more) on `diag_verdict_perturbed.set_images("dtu_s50:S")`; `mvgeo align`'s verified pairs are in its
  refusal messages or `AlignStats`;
- `mvgeo align` (`bench_real.OURS`, the calibration's EXIF focal) on the same photos blurred by a Gaussian of
  B px before the alignment (on top of the 1 px the detector applies): its registered views and rotation
  errors, or its refusal;
- pycolmap's global mapper with each camera model on clean and sigma-25 DTU (no EXIF focal).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2  # noqa: F401  before pycolmap (a PNG write after the reverse order aborts)
import numpy as np
from _common import cli_option, md_table
from bench_real import OURS, colmap_verified_pairs, exif_focal_35mm_of
from diag_verdict_perturbed import _variant, set_images

from mvgeo.align.api import align_images
from mvgeo.align.colmap_sfm import ColmapConfig, run_colmap
from mvgeo.common.errors import DgsError
from mvgeo.common.imageio import read_image, write_image
from mvgeo.metrics import compare_poses


def _pairs(seeds: list[str]) -> str:
    rows = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            paths, _, _ = set_images(f"dtu_s50:{seed}", Path(tmp))
            rows.append([f"dtu_s50:{seed}", colmap_verified_pairs(paths[0].parent, [p.name for p in paths])])
    return md_table(["photos", "pycolmap verified pairs (of 66)"], rows)


def _blur(seeds: list[str], blurs: list[float]) -> str:
    rows = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            paths, gt, K = set_images(f"dtu_s50:{seed}", work)
            h, w = read_image(paths[0]).shape[:2]
            mm = exif_focal_35mm_of(K, (w, h))
            for b in blurs:
                folder = work / f"blur{b}"
                folder.mkdir()
                for p in paths:
                    im = read_image(p)
                    write_image(folder / p.name, cv2.GaussianBlur(im, (0, 0), b) if b > 0 else im)
                tagged = _variant(sorted(folder.iterdir()), work / f"exif{b}", mm, "none")
                try:
                    m = compare_poses(align_images(tagged, OURS).sparse_model.cam_from_world_by_name(), gt)
                    out = f"{m.n_registered}/{m.n_ref}, {m.median_rotation_deg:.3f} / {m.rotation_deg.max():.2f} deg"
                except DgsError as exc:
                    out = f"{type(exc).__name__}: {str(exc)[:120]}"
                rows.append([f"dtu_s50:{seed}", b, out])
    return md_table(["photos", "blur (px)", "mvgeo align"], rows)


def _models(sets: list[str], models: list[str]) -> str:
    rows = []
    for name in sets:
        with tempfile.TemporaryDirectory() as tmp:
            paths, gt, _ = set_images(name, Path(tmp))
            for model in models:
                try:
                    res = run_colmap(paths[0].parent, ColmapConfig(mapper="global", camera_model=model),
                                     image_names=[p.name for p in paths])
                    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
                    params = np.round(next(iter(res.sparse_model.cameras.values())).params, 4).tolist()
                    rows.append([name, model, f"{m.n_registered}/{m.n_ref}", f"{m.median_rotation_deg:.3f}",
                                 f"{m.rotation_deg.max():.3f}", params])
                except DgsError as exc:
                    rows.append([name, model, f"failed: {type(exc).__name__}", "", "", ""])
    return md_table(["set", "camera model", "registered", "rot med (deg)", "rot max (deg)", "camera"], rows)


def main() -> int:
    print(_pairs(cli_option("seeds", "0,1").split(",")))
    print()
    print(_blur(cli_option("blur-seeds", "0,1,2,3").split(","),
                [float(b) for b in cli_option("blur", "0,1.0,1.7").split(",")]))
    print()
    print(_models(cli_option("model-sets", "dtu,dtu_noisy").split(","),
                  cli_option("models", "SIMPLE_RADIAL,SIMPLE_PINHOLE").split(",")))
    return 0


if __name__ == "__main__":
    sys.exit(main())

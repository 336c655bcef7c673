"""The training photos' own scores: PSNR, SSIM and LPIPS of each folder's photos against the clean ones.

What a splat trained on photos can reach depends on them: with the true cameras, the held-out LPIPS of the
splat of a method's photos is about the clean photos' splat's plus what the photos lose against the clean
ones (docs/bench/pipeline.md). This prints, for each folder, the mean over its photos (every image file in it
whose name is also in CLEAN_DIR), and the worst photo.

Usage: .venv/bin/python benchmarks/diag_photo_scores.py CLEAN_DIR DIR [DIR ...]
(e.g. CLEAN_DIR = a dataset's `clean/`, DIR = an evaluation's `runs/SCENE/seedK/product/round1/denoised` or
the dataset's `images/`)
"""
import argparse
import sys
from pathlib import Path

import numpy as np

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from eval.image_metrics import score_images
from mvgeo.common.imageio import read_image

_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff"}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clean_dir", type=Path)
    ap.add_argument("dirs", type=Path, nargs="+")
    args = ap.parse_args()
    print("| photos | n | PSNR | SSIM | LPIPS | worst LPIPS |")
    print("|---|---|---|---|---|---|")
    for folder in args.dirs:
        names = sorted(p.name for p in folder.iterdir()
                       if p.suffix.lower() in _SUFFIXES and (args.clean_dir / p.name).is_file())
        if not names:
            print(f"{folder}: no photo also in {args.clean_dir}", file=sys.stderr)
            return 2
        s = score_images([read_image(folder / n) for n in names], [read_image(args.clean_dir / n) for n in names])
        print(f"| {folder} | {len(names)} | {np.mean(s.psnr_db):.2f} | {np.mean(s.ssim):.3f} | "
              f"{np.mean(s.lpips):.3f} | {np.max(s.lpips):.3f} ({names[int(np.argmax(s.lpips))]}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

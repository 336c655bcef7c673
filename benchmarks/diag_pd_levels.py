"""The noise levels `denoise.pixel_shuffle.choose_stride` reads on photo folders, and the stride it chooses.

For each folder: the PCA noise level (/255) on the photos and on their pixel-shuffled sub-images by stride,
the stride, and the seconds the reading took (at most `MAX_PHOTOS` photos spread over the folder's sorted
image files).

Usage: .venv/bin/python benchmarks/diag_pd_levels.py FOLDER [FOLDER ...]
(e.g. a `denoise-gs dataset import` folder's `images/` or `clean/`)
"""
import sys
import time
from pathlib import Path

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from denoise.pixel_shuffle import choose_stride
from mvgeo.common.imageio import list_images, read_image


def main() -> int:
    if len(sys.argv) < 2:
        print(__doc__.strip().splitlines()[-2], file=sys.stderr)
        return 2
    print("| photos | level /255 by stride | stride | reading (s) |")
    print("|---|---|---|---|")
    for folder in sys.argv[1:]:
        images = [read_image(f) for f in list_images(Path(folder))]
        t = time.perf_counter()
        read = choose_stride(images)
        levels = ", ".join(f"{k}: {255.0 * v:.2f}" for k, v in read.level_by_stride.items())
        print(f"| {folder} | {levels} | {read.stride} | {time.perf_counter() - t:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Views of a run are named by the stem of their input file (`IMG_0001.JPG` -> `IMG_0001`).

Every stage writes `<stem>.png`, so noisy inputs, denoised images, renders and
COLMAP image names match by stem whatever the input format was.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from mvgeo.common.errors import InputError
from mvgeo.common.imageio import check_distinct_stems, list_images, read_image, write_image

__all__ = ["read_views", "view_files", "write_views"]


def view_files(folder: Path) -> dict[str, Path]:
    """Stem -> image file in `folder`, sorted by stem.

    Raises:
        InputError: no images, or two files share a stem, case aside (`a.png` and `A.jpg`).
    """
    paths = list_images(folder)
    check_distinct_stems([p.name for p in paths], path=folder)
    return dict(sorted((p.stem, p) for p in paths))


def read_views(folder: Path, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Stem -> (H, W, 3) float32 image, for `names` (default: all, sorted).

    Raises:
        InputError: a requested view is missing, or a file cannot be read.
    """
    files = view_files(folder)
    wanted = list(files) if names is None else list(names)
    missing = [n for n in wanted if n not in files]
    if missing:
        raise InputError(f"views {missing} are missing", path=folder)
    return {n: read_image(files[n]) for n in wanted}


def write_views(folder: Path, images: dict[str, np.ndarray]) -> None:
    """Write `<stem>.png` files, 16-bit so later stages see no 8-bit quantisation."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, img in images.items():
        write_image(folder / f"{name}.png", np.clip(img, 0.0, 1.0), bits=16)

"""The alignment's first stage: the images, checked, undistorted with known intrinsics and downscaled once."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mvgeo.align.intrinsics import undistort_image
from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image
from mvgeo.common.threads import pool_threads

__all__ = ["AlignInputs", "load_inputs"]


@dataclass(frozen=True)
class AlignInputs:
    """The views being aligned.

    Attributes:
        names: image names (unique).
        images: N (H0, W0, 3) float32 RGB in [0, 1] at the input size (undistorted with known intrinsics).
        small: the same at the alignment size (long side <= `AlignConfig.max_size_px`).
        input_wh: (W0, H0); align_wh: (Wa, Ha).
        intrinsics: the known camera at the input size, or None.
        K_align: (N, 3, 3) known intrinsics at the alignment size, or None.
    """

    names: list[str]
    images: list[np.ndarray]
    small: list[np.ndarray]
    input_wh: tuple[int, int]
    align_wh: tuple[int, int]
    intrinsics: Camera | None
    K_align: np.ndarray | None

    def __len__(self) -> int:
        return len(self.names)

    def restricted(self, keep: Sequence[int]) -> AlignInputs:
        """Only the views `keep`, in that order."""
        return replace(self, names=[self.names[v] for v in keep], images=[self.images[v] for v in keep],
                       small=[self.small[v] for v in keep],
                       K_align=None if self.K_align is None else self.K_align[list(keep)])


def _read(images: Sequence[Path] | Sequence[np.ndarray], names: Sequence[str] | None
          ) -> tuple[list[np.ndarray], list[str], list[Path]]:
    if len(images) < 2:
        raise InputError(f"need at least 2 images, got {len(images)}", fix="add more views of the scene")
    if all(isinstance(x, (str, Path)) for x in images):
        paths = [Path(x) for x in images]
        # Decoding and the float conversion release the GIL: the caller's threads (`pool_threads`). `map` returns
        # in order and raises the first unreadable file's error in file order, as the serial loop did.
        with ThreadPoolExecutor(max_workers=pool_threads(None, len(paths))) as pool:
            arrays = list(pool.map(read_image, paths))
        names = list(names) if names is not None else [p.name for p in paths]
    else:
        arrays = [np.asarray(x, np.float32) for x in images]
        names = list(names) if names is not None else [f"{k:03d}.png" for k in range(len(arrays))]
        paths = [Path(n) for n in names]
    return arrays, names, paths


def load_inputs(images: Sequence[Path] | Sequence[np.ndarray], *, names: Sequence[str] | None,
                intrinsics: Camera | None, max_size_px: int) -> AlignInputs:
    """Read and check the images (at least 2, unique names, one size, no duplicates), undistort them with
    `intrinsics`, and downscale them to `max_size_px` on the long side.

    Raises:
        InputError: too few, unreadable, duplicate or mixed-size images, or intrinsics of another size.
    """
    arrays, names, paths = _read(images, names)
    if len(set(names)) != len(names):
        raise InputError("image names are not unique")
    sizes = {a.shape[:2] for a in arrays}
    if len(sizes) > 1:
        listing = ", ".join(f"{n}: {a.shape[1]}x{a.shape[0]}" for n, a in zip(names, arrays, strict=True))
        a, b, *more = sorted(sizes)
        turned = not more and a == b[::-1]  # portrait and landscape photos of one camera
        raise InputError(f"images have different sizes ({listing})",
                         fix="mvgeo align assumes one camera: " + (
                             "rotate the photos to one orientation first, without resizing (the same camera "
                             "turned by 90 degrees)" if turned else "resize/crop all images to one size first"))
    seen: dict[str, str] = {}
    for n, a in zip(names, arrays, strict=True):
        h = hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()
        if h in seen:
            raise InputError(f"images {seen[h]!r} and {n!r} are identical (duplicate views carry no geometry)",
                             path=paths[names.index(n)], fix="remove one of them")
        seen[h] = n
    H0, W0 = arrays[0].shape[:2]
    if intrinsics is not None:
        if (intrinsics.width, intrinsics.height) != (W0, H0):
            raise InputError(f"intrinsics are for {intrinsics.width}x{intrinsics.height} images, "
                             f"the images are {W0}x{H0}", fix="pass the calibration of these images")
        arrays = [undistort_image(a, intrinsics) for a in arrays]
    s = min(1.0, max_size_px / max(H0, W0))
    Ha, Wa = max(1, round(H0 * s)), max(1, round(W0 * s))
    small = [a if (Ha, Wa) == (H0, W0) else cv2.resize(a, (Wa, Ha), interpolation=cv2.INTER_AREA) for a in arrays]
    K_align = None
    if intrinsics is not None:
        K = intrinsics.K.copy()
        K[0] *= Wa / W0
        K[1] *= Ha / H0
        K_align = np.repeat(K[None], len(arrays), axis=0)
    return AlignInputs(names, arrays, small, (W0, H0), (Wa, Ha), intrinsics, K_align)

"""Blind estimate of additive Gaussian noise (Immerkaer 1996, "Fast noise variance estimation").

scikit-image's `estimate_sigma` needs PyWavelets, which the project does not
ship; Immerkaer's estimator needs one 3x3 filter: the mask
`[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]` (the difference of two Laplacians)
cancels locally planar image structure, and for white noise of standard
deviation sigma, `E|I * M| = sigma * sqrt(2 / pi) * 6`.
"""

from __future__ import annotations

import numpy as np

from mvgeo.common.deps import cv2
from mvgeo.common.errors import ShapeError

__all__ = ["estimate_noise_sigma"]

_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)


def estimate_noise_sigma(img: np.ndarray) -> float:
    """Noise standard deviation of an (H, W) or (H, W, C) image, averaged over channels.

    Image units (e.g. [0, 1] images give sigma in [0, 1] units). Texture
    biases the estimate upward; the border row/column is excluded.

    Raises:
        ShapeError: fewer than 3 pixels along a side.
    """
    a = np.asarray(img, np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or min(a.shape[:2]) < 3:
        raise ShapeError(f"img: expected (H, W) or (H, W, C) with H, W >= 3, got {np.shape(img)}")
    sigmas = []
    for c in range(a.shape[2]):
        r = cv2.filter2D(a[:, :, c], cv2.CV_64F, _MASK, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
        sigmas.append(np.sqrt(np.pi / 2.0) * np.abs(r).mean() / 6.0)
    return float(np.mean(sigmas))

"""Fast noise-level estimates (Immerkær 1996): a mean-based one and a robust median-based one.

``sigma = sqrt(pi / 2) / (6 (W - 2) (H - 2)) * sum |I * M|`` with the 3x3
Laplacian-difference mask ``M = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``,
which cancels image structure up to second order, on the grayscale image over
the valid (interior) pixels. Strong edges and fine texture bias it upwards,
never downwards, so a small estimate is reliable evidence of a clean image.
"""

from __future__ import annotations

import numpy as np

from mvgeo.common.deps import cv2

_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float64)


def estimate_noise_sigma(img: np.ndarray) -> float:
    """Standard deviation of additive white noise, in the image's units ([0, 1]).

    Args:
        img: ``(H, W, 3)`` RGB or ``(H, W)`` / ``(H, W, 1)`` gray; images under 3x3 return 0.
    """
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 3:
        a = a.mean(axis=2)  # equal weights keep white noise white (std / sqrt(3) if independent per channel)
    h, w = a.shape
    if h < 3 or w < 3:
        return 0.0
    conv = cv2.filter2D(a, cv2.CV_64F, _MASK)[1:-1, 1:-1]
    sigma = np.sqrt(np.pi / 2) * np.abs(conv).sum() / (6.0 * (w - 2) * (h - 2))
    if np.asarray(img).ndim == 3 and np.asarray(img).shape[2] == 3:
        sigma *= np.sqrt(3.0)  # back to per-channel noise, assuming independent channels
    return float(sigma)


def estimate_noise_sigma_robust(img: np.ndarray) -> float:
    """Median-based noise std: ``median |I * M| / (6 * 0.6745)`` per channel, median over channels.

    For white Gaussian noise of std ``s``, ``I * M`` has std ``6 s`` (``sum M^2 = 36``)
    and ``median |N(0, 1)| = 0.6745``. The median ignores the edges and texture that
    inflate `estimate_noise_sigma` (measured on data_synth views with sigma 25/255:
    32/255 mean-based vs 27.7/255 here; the remainder is pixel-scale texture grain
    that no estimator can tell from noise: 11/255 on the *clean* views). Used to
    weight the observation in `denoise.fusion`.

    Args:
        img: ``(H, W, 3)`` RGB or ``(H, W)`` / ``(H, W, 1)`` gray; images under 3x3 return 0.
    """
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.shape[0] < 3 or a.shape[1] < 3:
        return 0.0
    per_channel = [np.median(np.abs(cv2.filter2D(a[:, :, c], cv2.CV_64F, _MASK)[1:-1, 1:-1])) / (6.0 * 0.6745)
                   for c in range(a.shape[2])]
    return float(np.median(per_channel))

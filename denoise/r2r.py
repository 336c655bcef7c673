"""Recorrupted-to-Recorrupted (Pang et al. 2021): Noise2Noise pairs from one image with known noise level.

For ``y = x + n``, ``n ~ N(0, sigma^2 I)``, and an independent ``z ~ N(0, sigma^2 I)``:
``y_in = y + alpha z`` and ``y_tgt = y - z / alpha`` have *independent* noise
(``cov(n + alpha z, n - z / alpha) = sigma^2 - sigma^2 = 0``) and the same mean
``x``, so the mean-squared error ``|f(y_in) - y_tgt|^2`` is, in expectation, the
supervised error of `f` on inputs of noise std ``sigma sqrt(1 + alpha^2)`` plus a
constant. The network therefore learns to denoise slightly noisier inputs; at
inference the paper averages ``f(y + alpha z_k)`` over several draws ``z_k``
(`denoise.self_supervised.denoise_with_method`).

The noise std must be known: the project estimates it per image with
`denoise.noise_level.estimate_noise_sigma_pca` (the benchmark's true sigma is not used).
"""

from __future__ import annotations

import torch
from torch import Tensor

from mvgeo.common.errors import check_shape


def recorrupt(y: Tensor, sigma: Tensor | float, *, alpha: float = 0.5,
              generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """One recorrupted pair ``(y + alpha z, y - z / alpha)`` with ``z ~ N(0, sigma^2)``.

    Args:
        y: ``[B, C, H, W]`` noisy batch.
        sigma: noise std of `y`, a float or a tensor broadcastable to `y` (e.g. ``[B, C, 1, 1]``
            or per pixel ``[B, C, H, W]``), in the units of `y`.
        alpha: recorruption scale (> 0).
        generator: source of `z` (on `y`'s device).

    Returns:
        ``(input, target)``, each shaped like `y`.
    """
    check_shape(y, ["B", "C", "H", "W"], "y")
    if not alpha > 0:
        raise ValueError(f"alpha must be > 0, got {alpha}")
    z = torch.randn(y.shape, generator=generator, device=y.device, dtype=y.dtype) * sigma
    return y + alpha * z, y - z / alpha

"""Empirical Wiener refinement of a denoised photo in a sliding-window DCT.

A denoiser's output (the pilot) estimates the clean photo's energy in each DCT coefficient of every
overlapping ``b x b`` block; the noisy photo's coefficients are shrunk by the Wiener gain that energy
implies, ``w = P^2 / (P^2 + sigma^2)``, and the blocks are put back together with weights
``1 / (sigma^2 * sum w^2)`` (blocks whose estimate keeps less noise count more). The refined photo is a
linear, locally adaptive filter of the *noisy* photo, so detail the pilot smoothed away but whose energy it
still shows comes back, and what the pilot invented without support in the noisy photo is damped. This is
the second step of the classical pilot-then-Wiener denoisers (e.g. Yu and Sapiro's sliding-window DCT
denoising), here on a learned pilot, without any grouping of similar blocks.

Colour photos are filtered in an orthonormal opponent colour space (luminance and two chrominances), where
independent per-channel noise stays independent with the same variance. The noise std may be one number or
a per-pixel, per-channel map (signal-dependent noise): a block's coefficient variance is then the mean of
the pixel variances in the block.

Measured with the `default` preset's photos as pilots (whole photos, 12 x 12 blocks, step 2, the noise std
the denoise stage estimates): DTU scan24 at sigma 25/255 30.43 -> 31.30 dB (29.83 -> 30.59 where the photos
are textured), the temple ring 34.18 -> 36.02 dB (docs/bench/denoise_real.md, "The DCT Wiener step").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.fft import dctn, idctn

__all__ = ["OPPONENT", "WienerConfig", "block_origins", "box_sums", "dct_wiener", "dct_wiener_gray"]

#: Orthonormal opponent colour transform (rows: luminance, red-blue, green-magenta): ``opp = OPPONENT @ rgb``.
OPPONENT = np.array([[1.0, 1.0, 1.0], [1.0, 0.0, -1.0], [1.0, -2.0, 1.0]]) / np.array(
    [[np.sqrt(3.0)], [np.sqrt(2.0)], [np.sqrt(6.0)]])


@dataclass(frozen=True)
class WienerConfig:
    """The sliding-window DCT Wiener step.

    Attributes:
        block_px: block side (DCT size). On four real sets (DTU scan24 and the temple ring, Gaussian sigma 25
            and Poisson-Gaussian noise) 12 gave 0.13-0.32 dB more than 8, and 16 (step 4) about the same as 12.
        step_px: distance between block origins (1: every block; with 8 px blocks, 1 gave 0.1 dB more than 2
            at three to four times the time); the last row and column of blocks always ends at the photo's
            edge.
        rows_per_chunk: block rows processed together (bounds memory: a chunk holds
            ``rows_per_chunk * n_cols * block_px^2`` coefficients, four arrays of them).
    """

    block_px: int = 12
    step_px: int = 2
    rows_per_chunk: int = 32

    def __post_init__(self):
        if self.block_px < 2 or self.step_px < 1 or self.step_px > self.block_px or self.rows_per_chunk < 1:
            raise ValueError(f"invalid WienerConfig {self}: need block_px >= 2, 1 <= step_px <= block_px, "
                             "rows_per_chunk >= 1")


def block_origins(n: int, block: int, step: int) -> np.ndarray:
    """Block origins along one axis of length `n`: every `step` px, and one ending at the edge."""
    o = np.arange(0, n - block + 1, step)
    return o if o[-1] == n - block else np.append(o, n - block)


def box_sums(a: np.ndarray, block: int) -> np.ndarray:
    """Sum of the ``(H, W)`` array `a` over every ``block x block`` window, by an integral image:
    ``(H - block + 1, W - block + 1)``, entry ``(i, j)`` for the window whose top-left pixel is ``(i, j)``."""
    ii = np.pad(np.cumsum(np.cumsum(a, 0), 1), ((1, 0), (1, 0)))
    return ii[block:, block:] - ii[:-block, block:] - ii[block:, :-block] + ii[:-block, :-block]


def dct_wiener_gray(noisy: np.ndarray, pilot: np.ndarray, variance: float | np.ndarray,
                    config: WienerConfig = WienerConfig()) -> np.ndarray:
    """One channel: the noisy ``(H, W)`` photo filtered with the Wiener gains of the ``(H, W)`` pilot.

    Args:
        noisy, pilot: ``(H, W)`` arrays (any float dtype; computed in float64).
        variance: the noise variance, one number or ``(H, W)`` per pixel.
        config: `WienerConfig`.

    Returns:
        ``(H, W)`` float64. Photos smaller than a block are returned as the pilot.
    """
    y = np.asarray(noisy, np.float64)
    p = np.asarray(pilot, np.float64)
    if y.shape != p.shape or y.ndim != 2:
        raise ValueError(f"noisy {y.shape} and pilot {p.shape} must be the same (H, W)")
    H, W = y.shape
    b = config.block_px
    if H < b or W < b:
        return p.copy()
    ys, xs = block_origins(H, b, config.step_px), block_origins(W, b, config.step_px)
    var = np.broadcast_to(np.asarray(variance, np.float64), (H, W))
    # Mean pixel variance of every block, floored so a noise-free photo comes back as is.
    block_var = np.maximum(box_sums(var, b) / (b * b), 1e-12)
    Y_all, P_all = sliding_window_view(y, (b, b)), sliding_window_view(p, (b, b))
    num = np.zeros((H, W))
    den = np.zeros((H, W))
    for r0 in range(0, len(ys), config.rows_per_chunk):
        rows = ys[r0:r0 + config.rows_per_chunk]
        Y = dctn(Y_all[np.ix_(rows, xs)], axes=(2, 3), norm="ortho")
        P = dctn(P_all[np.ix_(rows, xs)], axes=(2, 3), norm="ortho")
        v = block_var[np.ix_(rows, xs)][:, :, None, None]
        gain = P * P / (P * P + v)
        est = idctn(gain * Y, axes=(2, 3), norm="ortho")
        weight = 1.0 / (v[:, :, 0, 0] * np.sum(gain * gain, axis=(2, 3)) + 1e-12 * v[:, :, 0, 0])
        est *= weight[:, :, None, None]
        row_parts, col_parts = _strided_parts(rows), _strided_parts(xs)
        for dy in range(b):
            for dx in range(b):
                for src_r, dst_r in row_parts:
                    for src_c, dst_c in col_parts:
                        dst = _shifted(dst_r, dst_c, dy, dx)
                        num[dst] += est[src_r, src_c, dy, dx]
                        den[dst] += weight[src_r, src_c]
    return num / den


def _strided_parts(idx: np.ndarray) -> list[tuple[slice, slice | np.ndarray]]:
    """Increasing unique indices as (positions in `idx`, the indices) parts: the longest evenly spaced run
    from the start as a slice (`block_origins` are evenly spaced but for a last one at the edge), the rest
    as an index array. Strided views add in place without numpy's fancy-indexing cost; every target
    element gets the same additions in the same order either way."""
    k = min(len(idx), 2)
    step = int(idx[1] - idx[0]) if len(idx) > 1 else 1
    while k < len(idx) and idx[k] - idx[k - 1] == step:
        k += 1
    parts: list[tuple[slice, slice | np.ndarray]] = [(slice(0, k), slice(int(idx[0]), int(idx[k - 1]) + 1, step))]
    if k < len(idx):
        parts.append((slice(k, len(idx)), idx[k:]))
    return parts


def _shifted(rows: slice | np.ndarray, cols: slice | np.ndarray, dy: int, dx: int):
    """The index of ``(rows + dy) x (cols + dx)`` for `_strided_parts`' parts (slices or index arrays)."""
    def shift(part, by):
        return slice(part.start + by, part.stop + by, part.step) if isinstance(part, slice) else part + by

    r, c = shift(rows, dy), shift(cols, dx)
    # One index array and one slice index their cross product as they are; two arrays need np.ix_.
    return np.ix_(r, c) if isinstance(r, np.ndarray) and isinstance(c, np.ndarray) else (r, c)


def dct_wiener(noisy: np.ndarray, pilot: np.ndarray, sigma: float | np.ndarray,
               config: WienerConfig = WienerConfig()) -> np.ndarray:
    """The noisy photo filtered with the Wiener gains of a denoised one (module docstring).

    Args:
        noisy: ``(H, W, 3)`` RGB or ``(H, W)`` gray, in ``[0, 1]``; three equal channels (a gray photo read as
            RGB) are filtered as gray, with the mean of the pilot's channels, and returned in three channels.
        pilot: the same photo denoised, same shape.
        sigma: the noise std: one number, or per pixel and channel ``(H, W, 3)`` (``(H, W)`` for gray).
        config: `WienerConfig`.

    Returns:
        The refined photo, float32, the shape of `noisy` (not clipped).
    """
    y = np.asarray(noisy, np.float64)
    p = np.asarray(pilot, np.float64)
    if y.shape != p.shape:
        raise ValueError(f"noisy {y.shape} and pilot {p.shape} differ in shape")
    var = np.asarray(sigma, np.float64) ** 2
    if y.ndim == 2:
        return dct_wiener_gray(y, p, var, config).astype(np.float32)
    if y.ndim != 3 or y.shape[2] != 3:
        raise ValueError(f"expected (H, W, 3) or (H, W), got {y.shape}")
    if (y == y[..., :1]).all():
        # A gray photo read as RGB: the same noise in every channel, not independent noise (the opponent space's
        # luminance would hold 3x the variance it assumes). Filtered as the gray photo, against the pilot's gray.
        gray = dct_wiener_gray(y[..., 0], p.mean(axis=2), var if var.ndim == 0 else var.mean(axis=2), config)
        return np.repeat(gray[..., None], 3, axis=2).astype(np.float32)
    yo, po = y @ OPPONENT.T, p @ OPPONENT.T
    # Independent channels: each opponent channel's variance is the OPPONENT-squared mix of the RGB ones.
    # (The rows are unit vectors: one variance for all RGB channels is the same in every opponent channel.)
    var_o = var if var.ndim == 0 else var @ (OPPONENT ** 2).T
    out = np.stack([dct_wiener_gray(yo[..., c], po[..., c], var_o if var_o.ndim == 0 else var_o[..., c], config)
                    for c in range(3)], axis=-1)
    return (out @ OPPONENT).astype(np.float32)

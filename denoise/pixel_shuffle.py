"""Pixel-shuffle downsampling (PD): denoising photos whose noise is correlated between neighbouring pixels.

A camera's demosaicing interpolates each pixel's missing colours from its neighbours' noisy samples (and its
other raw-to-RGB steps filter further), so the noise of a photo is correlated over a few pixels. The
self-supervised objectives here assume noise independent from pixel to pixel: N2V's blind spot predicts a
pixel from its neighbours, whose noise then carries the pixel's own; R2R recorrupts with white noise; the
noise-level estimators (`denoise.noise_level`) difference neighbouring pixels, which cancels correlated
noise. On bilinearly demosaiced Poisson-Gaussian noise R2R's estimate reads about a fifth of the true
level and the photos leave the denoiser nearly as noisy as they came (docs/bench/denoise_real.md).

PD with stride ``s`` splits an image into ``s * s`` sub-images, each of every ``s``-th pixel from one offset
(`pd_split`); noise correlated over fewer than ``s`` pixels is independent within a sub-image. The
denoiser runs on the sub-images as on photos, and `pd_merge` puts the pixels back (Zhou et al. 2020, "When
AWGN-based denoiser meets real noises"; Lee et al. 2022, AP-BSN). The price: each sub-image is the scene at
1/s of the resolution, so the denoiser sees fine texture aliased.

`choose_stride` measures the correlation from the photos (`noise_lag_correlation`) and returns 1 (no PD)
for independent noise: photos with white or Poisson-Gaussian noise are denoised exactly as without PD.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mvgeo.common.deps import cv2

__all__ = ["MAX_STRIDE", "MIN_NOISE_STD", "RESIDUAL_CORRELATION", "NoiseCorrelation", "choose_stride", "merge_std",
           "noise_lag_correlation", "pd_merge", "pd_split", "shuffled", "unshuffled"]

#: The largest stride `choose_stride` returns (16 sub-images; a 384 px photo's are 96 px).
MAX_STRIDE = 4
#: Correlation between neighbours (lag 1) above which the noise counts as correlated and PD is used. White
#: and Poisson-Gaussian noise read -0.07 to 0.01 at lags 1-4 on DTU scan24 and the temple ring (sigma 25 and
#: 50, Poisson-Gaussian); bilinearly demosaiced Poisson-Gaussian noise reads 0.38 at lag 1 and -0.05 at lag 2
#: on DTU scan24 (0.51 and 0.00-0.02 on flat synthetic patches, where its true correlations are 0.58 and
#: 0.13 along rows: the pixels 2 apart share some sensor sites, those 3 apart none).
MAX_CORRELATION = 0.1
#: Correlation at lag s under which stride s is taken (the smallest such s >= 2). The larger the stride, the
#: less of the scene's resolution each sub-image keeps: on DTU scan24's demosaiced noise stride 2 (true
#: correlation 0.13 left at lag 2) gave 32.61 dB and stride 3 (none left) 32.42 (docs/bench/denoise_real.md).
RESIDUAL_CORRELATION = 0.2
#: The lag whose differences stand for uncorrelated noise, and the share of pixels (the flattest) measured.
FAR_LAG = 7
FLAT_SHARE = 0.3
#: Fewest flat pixel pairs (per channel and axis) a measurement takes: the median of fewer is too noisy,
#: and a small image's "flattest" pixels still hold its shading (a 40 x 44 px synthetic scene with white
#: noise read correlations of 0.1-0.4). About a 100 x 100 px photo.
MIN_FLAT_PAIRS = 3000
#: Below this noise std (in [0, 1] units, from the far differences over the flattest pixels) the photos
#: count as having white noise or none, and no stride is chosen: the clean photos of DTU scan24 and of the
#: temple ring read 6.4 and 5.7 /255 there (texture), with lag-1 correlations of 0.17 and 0.50 (texture's, not
#: noise's); bilinearly demosaiced Poisson-Gaussian noise of gain 0.01 and read noise 5/255 reads 12.8 /255,
#: sigma 25/255 white noise 24.9.
MIN_NOISE_STD = 8.0 / 255.0


def pd_split(image: np.ndarray, stride: int) -> list[np.ndarray]:
    """The ``stride * stride`` sub-images ``image[r::stride, c::stride]``, row offset major.

    Args:
        image: (H, W) or (H, W, C).
        stride: >= 1; sizes not divisible by it give sub-images one pixel smaller at the larger offsets.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    return [np.ascontiguousarray(image[r::stride, c::stride]) for r in range(stride) for c in range(stride)]


def pd_merge(parts: Sequence[np.ndarray], stride: int, shape: tuple[int, ...]) -> np.ndarray:
    """The inverse of `pd_split`: the image of shape `shape` whose sub-images are `parts`."""
    if len(parts) != stride * stride:
        raise ValueError(f"{len(parts)} sub-images for stride {stride} (need {stride * stride})")
    out = np.empty(shape, dtype=np.result_type(*[np.asarray(p).dtype for p in parts]))
    for k, p in enumerate(parts):
        r, c = divmod(k, stride)
        target = out[r::stride, c::stride]
        if target.shape != np.shape(p):
            raise ValueError(f"sub-image {k} has shape {np.shape(p)}, expected {target.shape} for {shape}")
        out[r::stride, c::stride] = p
    return out


def shuffled(images: Sequence[np.ndarray], stride: int) -> list[np.ndarray]:
    """Every image's `pd_split` sub-images, image after image (``stride * stride`` each)."""
    return [part for im in images for part in pd_split(im, stride)]


def unshuffled(parts: Sequence[np.ndarray], stride: int, shapes: Sequence[tuple[int, ...]]) -> list[np.ndarray]:
    """The inverse of `shuffled`: the images of shapes `shapes` (their channels may differ from the parts')."""
    n = stride * stride
    if len(parts) != n * len(shapes):
        raise ValueError(f"{len(parts)} sub-images for {len(shapes)} images at stride {stride}")
    return [pd_merge(parts[i * n:(i + 1) * n], stride, tuple(shape[:2]) + tuple(np.shape(parts[i * n])[2:]))
            for i, shape in enumerate(shapes)]


def merge_std(parts: Sequence, stride: int, shape: tuple[int, ...]):
    """One image's noise std from its sub-images' (`denoise.self_supervised.r2r_noise_std`: numbers, or
    ``[C, h, w]`` tensors): their mean, or the maps put back together where any is a map (a number among
    maps becomes a constant map)."""
    import torch

    if not any(isinstance(p, torch.Tensor) for p in parts):
        return float(np.mean([float(p) for p in parts]))
    H, W = shape[:2]
    C = next(p for p in parts if isinstance(p, torch.Tensor)).shape[0]
    grid = pd_split(np.zeros((H, W)), stride)
    maps = [p.permute(1, 2, 0).numpy() if isinstance(p, torch.Tensor) else np.full(g.shape + (C,), float(p))
            for p, g in zip(parts, grid, strict=True)]
    return torch.from_numpy(pd_merge(maps, stride, (H, W, C))).permute(2, 0, 1).contiguous()


@dataclass(frozen=True)
class NoiseCorrelation:
    """What `choose_stride` measured.

    Attributes:
        stride: the chosen PD stride (1: the noise is independent between neighbouring pixels, or the
            photos are clean).
        lag_correlation: {lag: correlation of the noise between pixels that far apart}, median over the
            photos and mean over channels and the two axes, for lags 1 .. `MAX_STRIDE`.
        noise_std: the noise std at `FAR_LAG` in [0, 1] units (median over photos and channels).
    """

    stride: int
    lag_correlation: dict[int, float]
    noise_std: float


def noise_lag_correlation(image: np.ndarray, lags: Sequence[int] = (1, 2, 3, 4)) -> np.ndarray:
    """Correlation of a photo's noise between pixels `lags` apart, from its differences in flat regions.

    For noise of std s and correlation rho_k at lag k on a locally constant signal, the difference of two
    pixels k apart has mean square ``2 s^2 (1 - rho_k)``; at `FAR_LAG` the noise is taken as uncorrelated, so
    ``rho_k = 1 - (RMS_k / RMS_far)^2`` with the root mean square differences. Means of squares, not medians:
    demosaiced noise has another variance at each site of the Bayer cell, so pairs at odd and even lags mix
    other variances, and only the mean of the squares averages them alike (medians read 0.33 at lag 2 on
    bilinearly demosaiced noise whose correlation there is 0.13). The pairs measured are
    the pairs whose segment is among the `FLAT_SHARE` flattest (the largest gradient of the photo smoothed at
    2 px between the two pixels) away from clipping (smoothed values in [0.08, 0.92]), so that texture and
    edges add little to the differences.

    Args:
        image: (H, W, 3) in [0, 1] (or (H, W)); at least 2 * `FAR_LAG` pixels on each side.

    Returns:
        (C, len(lags) + 1): per channel, the correlations (the mean of the horizontal and vertical
        estimates), then the noise std from the far differences (``RMS_far / sqrt 2``); NaN where
        fewer than `MIN_FLAT_PAIRS` pairs are flat and unclipped.
    """
    a = np.asarray(image, np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    if min(a.shape[:2]) < 2 * FAR_LAG:
        raise ValueError(f"image {a.shape[:2]} too small to measure the noise's correlation")
    out = np.zeros((a.shape[2], len(lags) + 1))
    for c in range(a.shape[2]):
        y = a[:, :, c]
        smooth = cv2.GaussianBlur(y, (0, 0), 2.0)
        grad = np.hypot(cv2.Sobel(smooth, cv2.CV_64F, 1, 0), cv2.Sobel(smooth, cv2.CV_64F, 0, 1))
        out[c] = np.mean([_lag_correlation_along(y, smooth, grad, axis, lags) for axis in (0, 1)], axis=0)
    return out


def _shifted_pairs(arr: np.ndarray, k: int, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of `arr` and those `k` further along `axis`, as two equal arrays."""
    return (arr[k:], arr[:-k]) if axis == 0 else (arr[:, k:], arr[:, :-k])


def _lag_correlation_along(y, smooth, grad, axis: int, lags: Sequence[int]) -> np.ndarray:
    """`noise_lag_correlation` of one channel along one axis: (len(lags) + 1,), the noise std last."""
    def usable(k):  # unclipped pairs, and the largest gradient on the segment between them
        s1, s2 = _shifted_pairs(smooth, k, axis)
        n = s1.shape[axis]
        seg = np.maximum.reduce([np.take(grad, np.arange(m, m + n), axis=axis) for m in range(k + 1)])
        return (np.minimum(s1, s2) > 0.08) & (np.maximum(s1, s2) < 0.92), seg

    def rms(k, sel):
        y1, y2 = _shifted_pairs(y, k, axis)
        return float(np.sqrt(np.mean((y1 - y2)[sel] ** 2))) if sel.any() else 0.0

    ok_far, g_far = usable(FAR_LAG)
    if FLAT_SHARE * ok_far.sum() < MIN_FLAT_PAIRS:
        return np.full(len(lags) + 1, np.nan)
    flat = np.quantile(g_far[ok_far], FLAT_SHARE)
    far = rms(FAR_LAG, ok_far & (g_far <= flat))
    row = []
    for k in lags:
        ok, g = usable(k)
        row.append(1.0 - (rms(k, ok & (g <= flat)) / far) ** 2 if far > 0 else 0.0)
    return np.array(row + [far / np.sqrt(2.0)])


def choose_stride(images: Sequence[np.ndarray], *, max_stride: int = MAX_STRIDE,
                  max_correlation: float = MAX_CORRELATION) -> NoiseCorrelation:
    """1 (no PD) where the noise's correlation between neighbours is under `max_correlation`; else the smallest
    stride s >= 2 whose lag-s correlation is under `RESIDUAL_CORRELATION` (`max_stride` if none is).

    The correlation at each lag is the median over the photos of `noise_lag_correlation`'s mean over
    channels. Photos with noise under
    `MIN_NOISE_STD` get 1, and so do photos too small to measure (under `MIN_FLAT_PAIRS` flat pairs, or
    2 * `FAR_LAG` px a side).
    """
    lags = tuple(range(1, max_stride + 1))
    images = [im for im in images if min(np.shape(im)[:2]) >= 2 * FAR_LAG]
    per_photo = np.array([noise_lag_correlation(im, lags).mean(axis=0) for im in images]).reshape(-1, len(lags) + 1)
    per_photo = per_photo[np.isfinite(per_photo).all(axis=1)]  # (N, lags + 1), the measurable photos
    if not len(per_photo):
        return NoiseCorrelation(1, {}, float("nan"))
    rho = np.median(per_photo[:, :-1], axis=0)
    std = float(np.median(per_photo[:, -1]))
    stride = 1 if rho[0] < max_correlation else next(
        (k for k, r in zip(lags[1:], rho[1:], strict=True) if r < RESIDUAL_CORRELATION), max_stride)
    if std < MIN_NOISE_STD:
        stride = 1
    return NoiseCorrelation(int(stride), {int(k): round(float(r), 4) for k, r in zip(lags, rho, strict=True)},
                            round(std, 6))

"""Fast noise-level estimates (Immerkær 1996): mean-based, robust median-based, and per intensity.

``sigma = sqrt(pi / 2) / (6 (W - 2) (H - 2)) * sum |I * M|`` with the 3x3
Laplacian-difference mask ``M = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``,
which cancels image structure up to second order, on the grayscale image over
the valid (interior) pixels. Strong edges and fine texture bias it upwards,
never downwards, so a small estimate is reliable evidence of a clean image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import nnls
from torch import Tensor

from mvgeo.common.deps import cv2

_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float64)


def one_channel_if_equal(img: np.ndarray) -> np.ndarray:
    """`img` as an array; ``(H, W)`` (its first channel) where it is ``(H, W, C)`` with all channels equal.

    A gray photo read as RGB (`mvgeo.common.imageio.read_image` replicates its one channel) holds the same
    noise in every channel, not independent noise: its colour patches span a third of the patch space (the
    PCA tail of `estimate_noise_sigma_pca` read 0) and its luma holds the whole noise (`luma_noise_sigma`
    read it 1.5x too high). The estimators here read such a photo on its one channel.
    """
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] > 1 and bool((a == a[:, :, :1]).all()):
        return a[:, :, 0]
    return a


def estimate_noise_sigma(img: np.ndarray) -> float:
    """Standard deviation of additive white noise, in the image's units ([0, 1]).

    Args:
        img: ``(H, W, 3)`` RGB or ``(H, W)`` / ``(H, W, 1)`` gray (three equal channels count as gray,
            `one_channel_if_equal`); images under 3x3 return 0.
    """
    img = one_channel_if_equal(img)
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 3:
        a = a.mean(axis=2)  # equal weights keep white noise white (std / sqrt(3) if independent per channel)
    h, w = a.shape
    if h < 3 or w < 3:
        return 0.0
    conv = cv2.filter2D(a, cv2.CV_64F, _MASK)[1:-1, 1:-1]
    sigma = np.sqrt(np.pi / 2) * np.abs(conv).sum() / (6.0 * (w - 2) * (h - 2))
    if img.ndim == 3 and img.shape[2] == 3:
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


@dataclass(frozen=True)
class NoiseCurve:
    """Signal-dependent noise model ``var(y | x) = gain * x + floor`` (``[0, 1]`` units).

    Poisson-Gaussian noise ``y = a Poisson(x / a) + N(0, s^2)`` has ``gain = a`` and
    ``floor = s^2``; additive white Gaussian noise has ``gain = 0``.
    """

    gain: float
    floor: float

    def sigma_at(self, intensity: Tensor) -> Tensor:
        """Noise std at clean intensity `intensity` (any shape; clamped to ``[0, 1]`` first)."""
        var = self.gain * intensity.clamp(0.0, 1.0) + self.floor
        return var.clamp_min(0.0).sqrt()


def estimate_noise_curve(img: np.ndarray, *, bins: int = 8, patch_px: int = 5) -> NoiseCurve:
    """Fit ``var = gain * intensity + floor`` to per-intensity noise variances (a noise-level function).

    All ``patch_px x patch_px x C`` patches that touch neither 0 nor 1 (clipping shrinks
    the noise) are split into `bins` equal-count bins by their mean value; each bin's
    noise variance is the PCA tail estimate of `estimate_noise_sigma_pca` (structure and
    channel-correlated texture excluded), placed at the bin's median patch mean; a
    non-negative least-squares line is fitted through the bins (noise-level functions as
    in Liu et al. 2008 and Foi et al. 2008, with this local estimator). Within a patch the
    variance is taken as constant: fine for patches much darker or brighter than
    ``gain / floor`` apart.

    Args:
        img: ``(H, W, 3)`` RGB or ``(H, W)`` / ``(H, W, 1)`` gray in ``[0, 1]``.
        bins: number of intensity bins (>= 2).
        patch_px: patch side (>= 2).

    Returns:
        `NoiseCurve`; a flat one (``gain = 0``, ``floor`` = the PCA variance of all patches)
        when there are fewer unclipped patches than ``4 * bins * patch dimension`` (too few
        for the bins' covariances); ``(0, 0)`` for images smaller than a patch.
    """
    if bins < 2:
        raise ValueError(f"bins must be >= 2, got {bins}")
    patches = _patches(img, patch_px)
    if patches is None:
        return NoiseCurve(0.0, 0.0)
    unclipped = _unclipped(patches)
    if unclipped.shape[0] < 4 * bins * patches.shape[1]:
        return NoiseCurve(0.0, _pca_tail_variance(patches))  # too small to bin: one level for all
    patches = unclipped
    level = patches.mean(axis=1)
    order = np.argsort(level, kind="stable")
    xs, vs = [], []
    for chunk in np.array_split(order, bins):
        xs.append(np.median(level[chunk]))
        vs.append(_pca_tail_variance(patches[chunk]))
    design = np.stack([np.asarray(xs), np.ones(bins)], axis=1)
    (gain, floor), _ = nnls(design, np.asarray(vs))
    return NoiseCurve(float(gain), float(floor))


def _grid_step(h: int, w: int, patch_px: int, max_patches: int) -> int:
    """The stride (the same along both axes) that thins an image's patch positions to about `max_patches`."""
    n = (h - patch_px + 1) * (w - patch_px + 1)
    return max(1, int(np.ceil(np.sqrt(n / max_patches))))


def _patches(img: np.ndarray, patch_px: int, max_patches: int = 200000) -> np.ndarray | None:
    """Patches of `img` as rows ``(N, C * P * P)``, on a regular grid thinned to about `max_patches`; an image
    whose channels are all equal as one channel (`one_channel_if_equal`).

    None if the image is smaller than a patch.
    """
    if patch_px < 2:
        raise ValueError(f"patch_px must be >= 2, got {patch_px}")
    a = np.asarray(one_channel_if_equal(img), dtype=np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    h, w, c = a.shape
    if h < patch_px or w < patch_px:
        return None
    windows = np.lib.stride_tricks.sliding_window_view(a, (patch_px, patch_px), axis=(0, 1))
    step = _grid_step(h, w, patch_px, max_patches)
    return windows[::step, ::step].reshape(-1, c * patch_px * patch_px)  # copies only the subsample


def _unclipped(patches: np.ndarray) -> np.ndarray:
    """The rows (patches) that touch neither 0 nor 1: where the noise was not clipped."""
    return patches[(patches.min(axis=1) > 0.0) & (patches.max(axis=1) < 1.0)]


def _covariance_eigenvalues(patches: np.ndarray) -> np.ndarray:
    """The eigenvalues of the covariance of `patches` (rows), ascending, negatives from round-off set to 0."""
    # torch (float64), not numpy: once torch has run (the UNet), numpy's own BLAS threads
    # fight torch's OpenMP pool and this 75 x N product took 1.3 s instead of 0.1 s (measured).
    t = torch.from_numpy(np.ascontiguousarray(patches, dtype=np.float64))
    t = t - t.mean(dim=0)
    return torch.linalg.eigvalsh(t.T @ t / t.shape[0]).numpy().clip(min=0.0)


def _pca_tail_variance(patches: np.ndarray) -> float:
    """Mean of the longest tail of covariance eigenvalues whose mean does not exceed its median."""
    eig = _covariance_eigenvalues(patches)[::-1]
    for i in range(eig.size):
        tail = eig[i:]
        if tail.mean() <= np.median(tail):
            return float(tail.mean())
    return float(eig[-1])


#: `estimate_noise_sigma_pca(exclude_clipped=True)` keeps to the unclipped patches only where at least
#: this many per patch dimension remain (a 75-D covariance from 300+ samples; fewer: all patches).
MIN_UNCLIPPED_PER_DIM = 4


def estimate_noise_sigma_pca(img: np.ndarray, *, patch_px: int = 5, max_patches: int = 60000,
                             exclude_clipped: bool = False) -> float:
    """White-noise std from the smallest eigenvalues of the patch covariance (Chen et al. 2015).

    Image structure, texture grain included, lives in a few directions of the space of
    ``patch_px x patch_px x C`` patches; white noise adds ``sigma^2`` to every eigenvalue of
    their covariance. With eigenvalues sorted in decreasing order ``l_1 >= ... >= l_d``, the
    estimate is the mean of the longest tail ``l_i..l_d`` whose mean does not exceed its
    median (the tail left once the structured directions, which pull the mean up, are
    dropped): ``sigma = sqrt(mean(l_i..l_d))`` (Chen, Zhu & Heng, "An efficient statistical
    method for image noise level estimation", ICCV 2015, with this simplified stopping
    rule). Unlike `estimate_noise_sigma_robust` it is not inflated by pixel-scale texture
    that is correlated across channels (measured on data_synth clean views, sigma 25/255:
    25.3/255 here vs 28.1/255 robust; noise-free views: 3.4/255 vs 12.4/255). Clipping at 0
    and 1 removes noise and biases it low (sigma 50/255: 47/255): the estimate over all patches
    is the noise the image holds on average, clipped parts included. With `exclude_clipped`
    only the patches that touch neither 0 nor 1 count: the std of the noise where it was not
    clipped, the level a recorruption of the signal needs (`denoise.r2r`). Measured at sigma
    25/255: DTU scan24 photos 22.0-22.7/255 over all patches, 24.5-25.0/255 unclipped; the
    Middlebury temple on its black background about 10/255 over all patches.

    Args:
        img: ``(H, W, 3)`` RGB or ``(H, W)`` / ``(H, W, 1)`` gray in ``[0, 1]``.
        patch_px: patch side (>= 2).
        max_patches: patches used at most (a regular subsample of all positions).
        exclude_clipped: estimate from the unclipped patches (where at least
            ``MIN_UNCLIPPED_PER_DIM`` per patch dimension remain; else from all).

    Returns:
        The std in ``[0, 1]`` units; 0 for images smaller than a patch.
    """
    patches = _patches(img, patch_px, max_patches)
    if patches is None:
        return 0.0
    if exclude_clipped:
        unclipped = _unclipped(patches)
        if unclipped.shape[0] >= MIN_UNCLIPPED_PER_DIM * patches.shape[1]:
            patches = unclipped
    return float(np.sqrt(_pca_tail_variance(patches)))


#: `fit_clipped_noise_sigma`: intensity bins of the patches, patch side, and the search interval of sigma
#: ([0, 1] units). 3 x 3 x C patches: each bin's PCA tail then comes from ~7k 27-D samples, whose sample
#: eigenvalues spread less around the noise level than 75-D ones (the tail mean errs low with the spread):
#: on three temple photos at sigma 50/255 48.8-49.0/255 against 48.1-48.4 with 5 x 5 patches.
CLIPPED_FIT_BINS = 8
CLIPPED_FIT_PATCH_PX = 3
CLIPPED_FIT_RANGE = (0.5 / 255.0, 128.0 / 255.0)


def _surround_level(img: np.ndarray, patch_px: int, max_patches: int, ring_px: int = 5) -> np.ndarray:
    """Per patch of `_patches` (same grid and order), the mean intensity of the `ring_px`-wide square ring
    around it: the patch's level, measured on pixels whose noise is independent of the patch's own.
    (Binning patches by their own mean selects their noise: over black, the bin of the lowest means holds
    the patches whose noise clipped most, and both their mean and their variance read low.)"""
    a = np.asarray(img, dtype=np.float64)
    g = a.mean(axis=2) if a.ndim == 3 else a
    h, w = g.shape
    outer = patch_px + 2 * ring_px
    box = cv2.boxFilter(g, cv2.CV_64F, (outer, outer), normalize=False, borderType=cv2.BORDER_REFLECT,
                        anchor=(ring_px + patch_px // 2, ring_px + patch_px // 2))
    inner = cv2.boxFilter(g, cv2.CV_64F, (patch_px, patch_px), normalize=False, borderType=cv2.BORDER_REFLECT,
                          anchor=(patch_px // 2, patch_px // 2))
    ring = (box - inner) / (outer * outer - patch_px * patch_px)  # at each patch centre
    step = _grid_step(h, w, patch_px, max_patches)  # `_patches`' grid
    c = patch_px // 2
    return ring[c:h - patch_px + 1 + c:step, c:w - patch_px + 1 + c:step].reshape(-1)


def fit_clipped_noise_sigma(img: np.ndarray, *, patch_px: int = CLIPPED_FIT_PATCH_PX,
                            bins: int = CLIPPED_FIT_BINS, max_patches: int = 60000) -> float:
    """Std of Gaussian noise clipped to ``[0, 1]``, fitted to the noise the image holds at each intensity.

    All ``patch_px x patch_px x C`` patches (default 3 x 3), clipped ones included, are split into `bins`
    equal-count bins by the mean of the ring of pixels around them (`_surround_level`: not by their own
    mean, which would select their noise); in each bin the patches' mean ``m_b`` and noise variance
    ``v_b`` (the PCA tail of `estimate_noise_sigma_pca`, structure removed) are measured. For a candidate
    ``s`` a bin's clean level is the ``x`` whose clipped mean is ``m_b``
    (`denoise.clipping.undo_clipping_bias`) and its variance is predicted by
    `denoise.clipping.clipped_variance`; each bin's ``s`` equates the two (on a log grid over
    `CLIPPED_FIT_RANGE`, interpolated), and the median over the bins is returned (a bin that mixes black
    and bright pixels at an object's edge holds less noise than its mean level predicts). A black
    background (``x = 0``: ``m = 0.399 s``, ``v = 0.341 s^2``) thus measures the noise as a mid-grey wall
    does: Foi's clipped noise model ("Clipped noisy images: heteroskedastic modeling and practical
    denoising", Signal Processing 2009) with this module's variance estimate. Only the sides the photo is
    clipped on (`denoise.clipping.clipped_sides`) are modelled as clipped.

    Measured on the photos of the imported real sets (`images/`, 15-16 each): the temple ring at sigma
    50/255 (65 % of its area dark and clipped) 47.6-49.4/255 where the unclipped patches give 33.8-36.3; at
    sigma 25 23.6-24.7 (unclipped: 23.4-24.9); DTU scan24 at sigma 25 23.4-24.6 (24.5-25.0); synthetic dark
    photos (tests/denoise/test_noise_level.py) 1-2 % low.

    Returns:
        The std in ``[0, 1]`` units; 0 for images smaller than a patch.
    """
    from denoise.clipping import clipped_sides, clipped_variance, undo_clipping_bias

    img = one_channel_if_equal(img)
    patches = _patches(img, patch_px, max_patches)
    if patches is None:
        return 0.0
    low, high = clipped_sides(np.asarray(img))
    level = _surround_level(img, patch_px, max_patches)
    order = np.argsort(level, kind="stable")
    chunks = [c for c in np.array_split(order, bins) if len(c) >= 2]
    if not chunks:  # a single patch: no variance to measure
        return 0.0
    m = torch.tensor([patches[c].mean() for c in chunks], dtype=torch.float64)  # unselected: their own values
    v = np.maximum([_pca_tail_variance(patches[c]) for c in chunks], 1e-12)
    grid = np.exp(np.linspace(np.log(CLIPPED_FIT_RANGE[0]), np.log(CLIPPED_FIT_RANGE[1]), 97))  # 1.7 % apart
    # (bins, grid): the log of each bin's measured over its predicted variance at each candidate sigma.
    sig = torch.as_tensor(grid, dtype=torch.float64)[None, :]
    x = undo_clipping_bias(m[:, None].expand(-1, len(grid)), sig, low=low, high=high)
    pred = clipped_variance(x, sig, low=low, high=high).numpy()
    r = np.log(v)[:, None] - np.log(np.maximum(pred, 1e-12))
    # Each bin's own sigma (where its log-ratio crosses zero: the predicted variance grows with sigma), then
    # the median: a bin that mixes levels (black and object pixels at an edge) holds less noise than its mean
    # level predicts and would pull a joint fit low.
    below = r > 0  # measured above predicted: sigma larger than this grid value
    per_bin = []
    for b in range(len(chunks)):
        if below[b].all():  # more noise than the range's top predicts
            per_bin.append(grid[-1])
            continue
        k = int(np.argmax(~below[b]))  # the first grid value that predicts at least the measured variance
        if k == 0:
            per_bin.append(grid[0])
            continue
        lo, hi = np.log(grid[k - 1]), np.log(grid[k])
        t = r[b, k - 1] / (r[b, k - 1] - r[b, k])  # linear in log sigma between the two grid values
        per_bin.append(float(np.exp(lo + t * (hi - lo))))
    return float(np.median(per_bin))


def estimate_noise_sigma_clipped(img: np.ndarray, *, read_luma: bool = True) -> float:
    """Std of additive Gaussian noise in a photo that may be clipped at 0 and 1: the larger of
    `estimate_noise_sigma_pca` on the unclipped patches and `fit_clipped_noise_sigma`.

    Both err low, not high: the unclipped patches are a selection (patches whose noise happened to stay
    inside ``[0, 1]``), which at sigma 50/255 on a dark photo leaves mid-tones only and their truncated noise
    (the temple ring: 34-36/255); the fit reads 1-5 % low (temple at sigma 50: 47.6-49.4/255). Where little
    is clipped the unclipped estimate is the larger and is returned unchanged (DTU scan24 at sigma 25: every
    photo; the temple ring at sigma 25: 7 of 15, the fit raising the other eight by up to 0.5/255).

    A colour photo whose noise is chroma-subsampled (`chroma_subsampled_noise_sigma`: a JPEG's) gives the
    level its luma reads instead: its colour patches read the smoothed colour differences' 1/255. With
    `read_luma` False the luma is not read: for a caller that has found the photo not chroma-subsampled by
    `chroma_subsampled_noise_sigma` (its colour reading, the unclipped patches' alone, is never above this
    one's, so this one would not find it either).
    """
    img = one_channel_if_equal(img)
    colour = max(estimate_noise_sigma_pca(img, exclude_clipped=True), fit_clipped_noise_sigma(img))
    if read_luma and np.ndim(img) == 3 and np.shape(img)[2] == 3:
        luma = chroma_subsampled_sigma(colour, luma_noise_sigma(img, exclude_clipped=True))
        if luma is not None:
            return luma
    return colour


#: BT.601 luma weights, the Y of JPEG's YCbCr. White RGB noise of std ``s`` has std ``LUMA_GAIN * s`` in luma.
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
LUMA_GAIN = float(np.linalg.norm(LUMA_WEIGHTS))


def _luma(img: np.ndarray) -> np.ndarray:
    """``(H, W)`` float64 luma (``LUMA_WEIGHTS``) of an ``(H, W, 3)`` RGB image in ``[0, 1]``; exactly 1 where all
    three channels are at 1 (the weights sum to 1, but in float64 to 0.9999999999999999: a blown highlight
    would not count as clipped, `_unclipped`)."""
    a = np.asarray(img, np.float64)
    y = a @ np.asarray(LUMA_WEIGHTS)
    y[(a >= 1.0).all(axis=2)] = 1.0
    return y


#: A colour photo's noise counts as chroma-subsampled where its colour patches read under this fraction of the
#: level its luma reads (`luma_noise_sigma`). JPEG's 4:2:0 chroma subsampling averages the colour differences
#: over 2 x 2 pixels and its decoder interpolates them back, so the colour directions of a patch hold no fine
#: noise and the PCA estimator, which takes the quietest directions, reads the noise at 1/255 while the luma
#: keeps all of it. Measured (colour patches over luma): white noise and Poisson-Gaussian noise on DTU scan24
#: and the temple ring 0.94-1.0 as PNGs, 0.04-0.07 after a JPEG round trip at quality 90 (0.03-0.04 on flat
#: synthetic scenes at 75-95); demosaiced Poisson-Gaussian noise, correlated in the luma too, 0.25 on a flat
#: synthetic scene and 0.41 on DTU scan24 (0.13 as a JPEG, its luma 5.3/255); clean photos 0.25-0.39, and
#: 0.11-0.31 as JPEGs (their luma 0.8-3.6/255): the floor `MIN_LUMA_NOISE_STD` keeps those out.
CHROMA_DEFICIT_RATIO = 0.12
#: The luma level (RGB-equivalent, [0, 1] units) a chroma-subsampled reading needs: clean photos' texture reads
#: 0.8-3.6/255 in luma, demosaiced Poisson-Gaussian noise (gain 0.01, read 5/255) 4.7-5.4.
MIN_LUMA_NOISE_STD = 8.0 / 255.0


def luma_noise_sigma(img: np.ndarray, *, exclude_clipped: bool = False) -> float:
    """The std of white RGB noise that leaves `img`'s luma as noisy as it reads: `estimate_noise_sigma_pca` on
    the luma (``LUMA_WEIGHTS``), over ``LUMA_GAIN``. On white noise it reads as the colour patches do; where
    the colour differences were smoothed (JPEG's chroma subsampling) it still reads the noise the photo had.
    Three equal channels (a gray photo read as RGB, the same noise in each) read as that one channel.

    Args:
        img: ``(H, W, 3)`` RGB in ``[0, 1]``.
        exclude_clipped: as `estimate_noise_sigma_pca`'s.
    """
    gray = one_channel_if_equal(img)
    if gray.ndim == 2:  # a gray photo read as RGB: its luma is the channel, with all of its noise
        return estimate_noise_sigma_pca(gray, exclude_clipped=exclude_clipped)
    return estimate_noise_sigma_pca(_luma(img), exclude_clipped=exclude_clipped) / LUMA_GAIN


#: `luma_noise_spread`'s largest value for noise white in the luma: DTU scan24 with white noise at 10 and 25/255
#: or Poisson-Gaussian noise, JPEGs at quality 90, and the temple ring at 25/255, 1.04-1.20; flat synthetic
#: scenes 1.03. Demosaiced Poisson-Gaussian noise (gain 0.01, read 5/255) 2.9 on DTU scan24 as a JPEG at quality
#: 90, 3.8 as a PNG, 4.1-5.7 on the temple ring, 4.5 on flat synthetic scenes as a JPEG (the median over six
#: photos of each one's spread). Texture spreads the eigenvalues too where the noise is faint (DTU's clean photos
#: as JPEGs 4.1, with white noise of 5/255 2.7), but noise that faint is not read as a JPEG's
#: (`MIN_LUMA_NOISE_STD`).
WHITE_LUMA_MAX_SPREAD = 2.0


def luma_noise_spread(img: np.ndarray, *, patch_px: int = 5, max_patches: int = 60000) -> float:
    """How far the luma's noise is from white: the fifth smallest eigenvalue of the covariance of the luma's
    unclipped `patch_px` x `patch_px` patches over the smallest.

    White noise adds the same variance to every direction of the patch space, and the smallest eigenvalues,
    which image structure leaves alone, are alike (ratio about 1). Noise correlated between neighbouring pixels
    (a demosaicing's) holds little power at the finest scales and more at coarser ones: its eigenvalues spread
    (`WHITE_LUMA_MAX_SPREAD`). inf where the smallest eigenvalue is 0 (a flat image); nan for images under a
    patch or without 25 unclipped patches.

    Args:
        img: ``(H, W, 3)`` RGB in ``[0, 1]``.
    """
    patches = _patches(_luma(img), patch_px, max_patches)
    if patches is None:
        return float("nan")
    patches = _unclipped(patches)
    if patches.shape[0] < patches.shape[1]:
        return float("nan")
    eig = _covariance_eigenvalues(patches)
    return float(eig[4] / eig[0]) if eig[0] > 0 else float("inf")


def constant_noise_sigma_luma(img: np.ndarray) -> float:
    """The noise model ``"luma"``'s std of one image (`denoise.inference.NoiseModel`): `luma_noise_sigma` of its
    unclipped patches (a colour image), `estimate_noise_sigma_pca` of them (a gray one)."""
    img = one_channel_if_equal(img)
    if np.ndim(img) == 3 and np.shape(img)[2] == 3:
        return luma_noise_sigma(img, exclude_clipped=True)
    return estimate_noise_sigma_pca(img, exclude_clipped=True)


def chroma_subsampled_sigma(colour_sigma: float, luma_sigma: float) -> float | None:
    """`luma_sigma` where a photo whose colour patches read `colour_sigma` and whose luma reads `luma_sigma`
    (`luma_noise_sigma`) holds chroma-subsampled noise (``colour_sigma < CHROMA_DEFICIT_RATIO * luma_sigma``,
    ``luma_sigma >= MIN_LUMA_NOISE_STD``); None otherwise."""
    if luma_sigma >= MIN_LUMA_NOISE_STD and colour_sigma < CHROMA_DEFICIT_RATIO * luma_sigma:
        return float(luma_sigma)
    return None


def chroma_subsampled_noise_sigma(img: np.ndarray) -> float | None:
    """The luma's level (`luma_noise_sigma`, unclipped patches) where `img`'s noise is chroma-subsampled
    (`chroma_subsampled_sigma` against its colour patches' `estimate_noise_sigma_pca`); None for a photo
    whose colour patches read the noise, a clean one, or a gray one."""
    img = one_channel_if_equal(img)
    if np.ndim(img) != 3 or np.shape(img)[2] != 3:
        return None
    return chroma_subsampled_sigma(estimate_noise_sigma_pca(img, exclude_clipped=True),
                                   luma_noise_sigma(img, exclude_clipped=True))

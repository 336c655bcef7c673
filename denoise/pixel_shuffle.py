"""Pixel-shuffle downsampling (PD): denoising photos whose noise is correlated between neighbouring pixels.

A camera's demosaicing interpolates each pixel's missing colours from its neighbours' noisy samples (and its
other raw-to-RGB steps filter further), so the noise of a photo is correlated over a few pixels. The
self-supervised objectives here assume noise independent from pixel to pixel: N2V's blind spot predicts a
pixel from its neighbours, whose noise then carries the pixel's own; R2R recorrupts with white noise; the
noise-level estimators (`denoise.noise_level`) see noise that is smooth over a few pixels as image content.
On bilinearly demosaiced Poisson-Gaussian noise R2R's estimate reads under a quarter of the level and the
photos leave the denoiser nearly as noisy as they came (docs/bench/denoise_real.md).

PD with stride ``s`` splits an image into ``s * s`` sub-images, each of every ``s``-th pixel from one offset
(`pd_split`); noise correlated over fewer than ``s`` pixels is independent within a sub-image. The
denoiser runs on the sub-images as on photos, and `pd_merge` puts the pixels back (Zhou et al. 2020, "When
AWGN-based denoiser meets real noises"; Lee et al. 2022, AP-BSN). The price: each sub-image is the scene at
1/s of the resolution, so the denoiser sees fine texture aliased.

`choose_stride` finds the stride from the photos: the noise level the PCA estimator
(`denoise.noise_level.estimate_noise_sigma_pca`, which R2R's noise level starts from) reads on the photos and
on their sub-images. For
noise independent per pixel the two agree; correlated noise reads low on the photos and at its level on the
sub-images. Photos with white or Poisson-Gaussian noise get stride 1 and are denoised exactly as without PD.

A JPEG's noise reads low on the photos for another reason: its 4:2:0 chroma subsampling smooths the colour
differences, while the luma keeps its noise, white (`denoise.noise_level.CHROMA_DEFICIT_RATIO`). Where the
photos' luma reads the level their colour patches miss, the stride is 1 and the level is the luma's
(`NoiseLevels.luma_level`; the denoisers read each photo's level on its luma, `NoiseLevels.noise_model`). A
camera's JPEG holds both: demosaiced noise, correlated in the luma too (its patch eigenvalues spread,
`denoise.noise_level.luma_noise_spread`), under a subsampled chroma. Its stride is `JPEG_STRIDE` and its level
the one the sub-images' luma reads, since their colour patches read the subsampled colour differences.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["JPEG_HINT_CHROMA_RATIO", "JPEG_STRIDE", "MAX_PHOTOS", "MAX_STRIDE", "MIN_CORRELATED_NOISE_STD",
           "MIN_LEVEL_RATIO", "MIN_NOISE_STD", "STRONG_LEVEL_RATIO", "SUB_CHROMA_DEFICIT_RATIO", "NoiseLevels",
           "choose_stride", "luma_hint_text", "merge_std", "pd_merge", "pd_split", "shuffled", "stride_for",
           "unshuffled"]

#: The largest stride `choose_stride` returns (16 sub-images; a 384 px photo's are 96 px).
MAX_STRIDE = 4
#: The noise counts as correlated where the photos' noise level reads under this fraction of their stride-2
#: sub-images'. Independent noise reads 0.98-1.01 (DTU scan24 and the temple ring at sigma 25 and 50 and
#: with Poisson-Gaussian noise, the synthetic llff_like at sigma 25); bilinearly demosaiced Poisson-Gaussian
#: noise 0.16. A larger stride is taken while the next one still reads more than 1 / this as much noise.
MIN_LEVEL_RATIO = 0.8
#: Below this noise level in the stride-2 sub-images ([0, 1] units) no stride is chosen: a clean photo's
#: texture reads as a little noise that grows with the stride (the synthetic llff_like's clean views: 2.6
#: and 6.4 /255 at strides 1 and 2; DTU scan24's clean photos 0.9 and 1.3). The same scene with independent
#: noise of 5/255 reads 5.8 and 7.8 (a ratio of 0.75): only this floor keeps such faint noise at stride 1.
MIN_NOISE_STD = 8.0 / 255.0
#: Noise that reads under this fraction of its stride-2 level on the photos counts as correlated from the lower
#: floor `MIN_CORRELATED_NOISE_STD` up. Bilinearly demosaiced Poisson-Gaussian noise reads 0.13 (the temple
#: ring) and 0.16 (DTU scan24), 0.20-0.22 on flat synthetic scenes; clean photos' texture 0.32 (the synthetic
#: llff_like at 504 x 378; 0.41 at a smaller size), 0.54-0.55 (object_ring, hard_repetitive) and 0.69 (DTU scan24,
#: the temple ring); white noise 0.75 (5/255) to 1.0. A photo whose background is black and clipped (the temple
#: ring: 55 % of its area) reads its demosaiced noise at 6.6/255 in the stride-2 sub-images, under
#: `MIN_NOISE_STD`: the PCA estimator takes the level of its least noisy patches, the clipped dark ones.
STRONG_LEVEL_RATIO = 0.25
#: The stride-2 level a `STRONG_LEVEL_RATIO` reading needs ([0, 1] units): clean real photos read 0.4-1.3/255.
MIN_CORRELATED_NOISE_STD = 3.0 / 255.0
#: The stride for correlated noise under a JPEG's chroma subsampling (`choose_stride`). The colour levels that
#: climb the strides for other noise read the subsampled colour differences there (DTU scan24 with
#: `bayer-pg:0.01,5+jpeg:90`: 0.7, 3.7 and 6.4/255 at strides 1-3, which took stride 3), so the stride is the
#: one that decorrelates a demosaicing's noise. Measured on those photos (R2R, 2000 steps, the Wiener steps,
#: PSNR against the clean photos from 27.37 dB): stride 2 30.29 dB, stride 3 29.99 at the same level (11/255);
#: stride 2 at the level the sub-images' luma reads 31.44 (docs/bench/denoise_real.md).
JPEG_STRIDE = 2
#: Correlated noise counts as chroma-subsampled where the stride-2 sub-images' colour patches read under this
#: fraction of their luma's level. Measured: DTU scan24's demosaiced Poisson-Gaussian noise as a JPEG at quality
#: 90 0.19, its white noise of 25/255 as a JPEG 0.23; as PNGs, demosaiced noise 0.63 (0.84 on the temple ring)
#: and Poisson-Gaussian 0.69. (Clean photos read under it too, 0.04-0.08, their texture in the luma, but their
#: colour level is under `MIN_CORRELATED_NOISE_STD`: the noise does not count as correlated.)
SUB_CHROMA_DEFICIT_RATIO = 0.4
#: Photos whose colour patches read under this fraction of their luma's level look chroma-subsampled (a JPEG's)
#: to `choose_stride`'s hint (`NoiseLevels.luma_hint_level`). Measured on the photos: a camera's JPEGs of
#: demosaiced noise (`bayer-pg:0.01,5+jpeg:Q`, Q 70-95) 0.12-0.14 on DTU scan24 and 0.09-0.20 on the temple
#: ring, DTU's clean photos as JPEGs 0.11; as PNGs, demosaiced noise 0.41 (0.16 on the temple ring, where its
#: stride is found) and clean photos 0.25 (DTU) and 0.39 (the temple).
JPEG_HINT_CHROMA_RATIO = 0.2
#: Photos the levels are read on at most, spread over the list (about 0.3 s a photo and stride on one core
#: at 384 x 384).
MAX_PHOTOS = 6


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
    first = next(p for p in parts if isinstance(p, torch.Tensor))
    C, dtype = first.shape[0], first.numpy().dtype
    grid = pd_split(np.zeros((H, W)), stride)
    maps = [p.permute(1, 2, 0).numpy() if isinstance(p, torch.Tensor) else np.full(g.shape + (C,), float(p), dtype)
            for p, g in zip(parts, grid, strict=True)]
    return torch.from_numpy(pd_merge(maps, stride, (H, W, C))).permute(2, 0, 1).contiguous()


@dataclass(frozen=True)
class NoiseLevels:
    """What `choose_stride` read.

    Attributes:
        stride: the chosen PD stride (1: the noise is independent between neighbouring pixels, or weak).
        level_by_stride: {stride: the noise std the PCA estimator reads on the sub-images at that stride,
            [0, 1] units}, the median over each photo's sub-images, then over the photos read; stride 1 is the
            photos themselves. Strides past the one that decided are not read.
        luma_level: where the photos' noise is chroma-subsampled, the level their luma reads (RGB-equivalent,
            the median over the photos read, `denoise.noise_level.luma_noise_sigma`) at `stride`: white noise
            (`denoise.noise_level.chroma_subsampled_sigma` of the stride-1 level and this) at stride 1,
            correlated noise at `JPEG_STRIDE` (`choose_stride`); else None.
        luma_hint_level: where no noise was found (stride 1, the colour patches' level) but the photos look
            chroma-subsampled (colour patches under `JPEG_HINT_CHROMA_RATIO` of their luma) with a luma whose
            eigenvalues spread (not white), the level their stride-2 sub-images' luma reads, if at least
            `MIN_CORRELATED_NOISE_STD`: a camera's JPEG whose noise the colour patches cannot show (quality 80,
            a clipped black background), or a clean photo's texture aliased into the luma. Nothing acts on it;
            the run's report suggests `--pd-stride 2 --noise-model luma` for noisy photos. With a stride the
            user gave (`stride_for`; `level_by_stride` then holds only that stride), the level the sub-images'
            luma reads where their colour patches under-read it: the report suggests `--noise-model luma`.
            Else None.
    """

    stride: int
    level_by_stride: dict[int, float]
    luma_level: float | None = None
    luma_hint_level: float | None = None

    @property
    def noise_model(self) -> str:
        """The noise model the denoisers read each photo's level with (`denoise.inference.NoiseModel`):
        ``"luma"`` where the photos' noise is chroma-subsampled, else ``"auto"``."""
        return "auto" if self.luma_level is None else "luma"

    def levels_255(self) -> str:
        """The levels read, /255, for a log line ("not measured" when none were read)."""
        text = ", ".join(f"{k}: {255.0 * v:.1f}" for k, v in self.level_by_stride.items()) or "not measured"
        return text if self.luma_level is None else f"{text}; luma: {255.0 * self.luma_level:.1f}"

    def levels_by_stride_255(self) -> dict[str, float]:
        """The levels read, /255 rounded to 0.01, keyed by the stride as a string (a JSON key); empty when
        none were read."""
        return {str(k): round(255.0 * v, 2) for k, v in self.level_by_stride.items()}

    def record(self) -> dict[str, object]:
        """What `denoise n2v`'s report.json records: the stride, and the levels read (/255) if any."""
        levels = self.levels_by_stride_255()
        luma = {} if self.luma_level is None else {"noise_level_luma_255": round(255.0 * self.luma_level, 2)}
        if self.luma_hint_level is not None:
            luma["noise_level_luma_hint_255"] = round(255.0 * self.luma_hint_level, 2)
        return {"pd_stride": self.stride, **({"noise_level_by_stride_255": levels} if levels else {}), **luma}

    def hint(self) -> str | None:
        """Where `luma_hint_level` is set, what the user may try (a log line, the run's report); else None."""
        if self.luma_hint_level is None:
            return None
        if 1 in self.level_by_stride:  # found by `choose_stride`
            return luma_hint_text(255.0 * self.level_by_stride[1], 255.0 * self.luma_hint_level)
        return luma_hint_text(255.0 * self.level_by_stride[self.stride], 255.0 * self.luma_hint_level,
                              given_stride=self.stride)  # a stride the user gave (`stride_for`)


def luma_hint_text(colour_255: float, luma_255: float, *, given_stride: int | None = None) -> str:
    """The hint of `NoiseLevels.hint` from its two levels (/255): the photos' colour patches and their stride-2
    sub-images' luma (`choose_stride`), or, with `given_stride`, both read on the sub-images of the stride the
    user gave (`stride_for`)."""
    if given_stride is not None:
        return (f"--pd-stride {given_stride} was given, and the sub-images' colour patches read {colour_255:.1f}/255 "
                f"of noise where their luma reads {luma_255:.1f}/255, as in a camera's JPEG: the denoisers read "
                "each photo's level on its colour patches and would remove little of its noise; add --noise-model "
                "luma to read it on the luma (a clean photo's texture reads this way too)")
    return (f"the photos look like JPEGs (their colour patches read {colour_255:.1f}/255 of noise, their luma "
            f"much more) and their luma's 2 x 2 pixel-shuffled sub-images read {luma_255:.1f}/255: if the photos "
            "are visibly noisy (a camera's demosaiced noise, too faint in the colour patches to be found), "
            "denoise them with --pd-stride 2 --noise-model luma; a clean photo's texture reads this way too")


def stride_for(images: Sequence[np.ndarray], setting: int, *, hint: bool = True) -> NoiseLevels:
    """The stride a `pd_stride` setting gives: `choose_stride` for 0, else the setting.

    With a stride > 1 given and `hint` (the caller leaves the noise model to the `"auto"` rule,
    `denoise.inference.NoiseModel`, and reports the hint), the sub-images' colour patches and luma are read (as
    `choose_stride` reads them): where the colour patches read under `SUB_CHROMA_DEFICIT_RATIO` of a luma at
    least `MIN_CORRELATED_NOISE_STD`, `luma_hint_level` is the luma's level and `NoiseLevels.hint` says to add
    `--noise-model luma`. The "auto" model reads each photo's level on its colour patches, which a JPEG's chroma
    subsampling has smoothed: with the stride alone, a camera's JPEGs are denoised at a fraction of their
    noise. Nothing else is read, and nothing acts on the hint.
    """
    if setting == 0:
        return choose_stride(images)
    stride = int(setting)
    big = [im for im in images if min(np.shape(im)[:2]) >= 16 * stride]
    if (stride == 1 or not hint or not big
            or not all(np.ndim(im) == 3 and np.shape(im)[2] == 3 for im in big)):
        return NoiseLevels(stride, {})
    pick = _spread_pick(big)
    colour, luma = _level(pick, stride), _level(pick, stride, luma=True)
    hinted = colour < SUB_CHROMA_DEFICIT_RATIO * luma and luma >= MIN_CORRELATED_NOISE_STD
    return NoiseLevels(stride, {stride: round(colour, 6)}, luma_hint_level=round(luma, 6) if hinted else None)


def _spread_pick(images: Sequence[np.ndarray]) -> list[np.ndarray]:
    """At most `MAX_PHOTOS` of `images`, spread over the list."""
    if len(images) <= MAX_PHOTOS:
        return list(images)
    return [images[int(i)] for i in np.linspace(0, len(images) - 1, MAX_PHOTOS)]


def _level(images: Sequence[np.ndarray], stride: int, *, luma: bool = False) -> float:
    """The median over `images` of the median over each one's stride-`stride` sub-images of the level the PCA
    estimator reads on their colour patches (`luma`: on their luma, `denoise.noise_level.luma_noise_sigma`)."""
    from denoise.noise_level import estimate_noise_sigma_pca, luma_noise_sigma

    read = luma_noise_sigma if luma else estimate_noise_sigma_pca
    return float(np.median([np.median([read(p) for p in pd_split(im, stride)]) for im in images]))


def _luma_spread(images: Sequence[np.ndarray]) -> float:
    """The median over `images` of `denoise.noise_level.luma_noise_spread`."""
    from denoise.noise_level import luma_noise_spread

    return float(np.median([luma_noise_spread(im) for im in images]))


def choose_stride(images: Sequence[np.ndarray], *, max_stride: int = MAX_STRIDE,
                  min_ratio: float = MIN_LEVEL_RATIO) -> NoiseLevels:
    """1 (no PD) where the photos' noise is chroma-subsampled (a JPEG's: the module docstring), or where the
    noise level reads about the same on the photos as on their stride-2 sub-images
    (at least `min_ratio` of it), or is weak (under `MIN_NOISE_STD` there, unless the photos read under
    `STRONG_LEVEL_RATIO` of it and it is at least `MIN_CORRELATED_NOISE_STD`); else, where the stride-2 sub-images'
    colour patches read under `SUB_CHROMA_DEFICIT_RATIO` of their luma (correlated noise saved as a JPEG),
    `JPEG_STRIDE` with the level read on the luma; else the smallest stride s >= 2 whose level is at least
    `min_ratio` of stride s + 1's (`max_stride` at most). A JPEG's noise counts as white where its luma's
    eigenvalues do not spread (`denoise.noise_level.luma_noise_spread`).

    Reads at most `MAX_PHOTOS` photos, spread over the list; photos whose stride-`max_stride` sub-images
    would be under 16 px a side are not read, and without any other the stride is 1.
    """
    big = [im for im in images if min(np.shape(im)[:2]) >= 16 * max_stride]
    if not big:
        return NoiseLevels(1, {})
    pick = _spread_pick(big)
    from denoise.noise_level import WHITE_LUMA_MAX_SPREAD, chroma_subsampled_sigma

    level = {1: _level(pick, 1)}
    colour = all(np.ndim(im) == 3 and np.shape(im)[2] == 3 for im in pick)
    luma_1 = spread = None
    if colour:
        luma_1 = _level(pick, 1, luma=True)
        luma = chroma_subsampled_sigma(level[1], luma_1)
        if luma is not None:
            spread = _luma_spread(pick)
            if spread <= WHITE_LUMA_MAX_SPREAD:
                return NoiseLevels(1, {1: round(level[1], 6)}, round(luma, 6))  # a JPEG's noise: white in the luma
    level[2] = _level(pick, 2)
    stride = 1
    correlated = level[2] >= MIN_NOISE_STD and level[1] < min_ratio * level[2]
    strongly = level[2] >= MIN_CORRELATED_NOISE_STD and level[1] < STRONG_LEVEL_RATIO * level[2]
    if (correlated or strongly) and colour:
        luma_2 = _level(pick, JPEG_STRIDE, luma=True)
        if level[JPEG_STRIDE] < SUB_CHROMA_DEFICIT_RATIO * luma_2:
            # Correlated noise under a JPEG's chroma subsampling (a camera's demosaiced noise saved as a JPEG):
            # the sub-images' colour patches read the subsampled colour differences, not the noise.
            return NoiseLevels(JPEG_STRIDE, {k: round(v, 6) for k, v in level.items()}, round(luma_2, 6))
    if correlated or strongly:
        stride = 2
        while stride < max_stride:
            level[stride + 1] = _level(pick, stride + 1)
            if level[stride] >= min_ratio * level[stride + 1]:
                break
            stride += 1
    levels = {k: round(v, 6) for k, v in level.items()}
    if stride == 1 and colour and level[1] < JPEG_HINT_CHROMA_RATIO * luma_1:
        if (_luma_spread(pick) if spread is None else spread) > WHITE_LUMA_MAX_SPREAD:
            luma_2 = _level(pick, JPEG_STRIDE, luma=True)
            if luma_2 >= MIN_CORRELATED_NOISE_STD:
                return NoiseLevels(1, levels, luma_hint_level=round(luma_2, 6))
    return NoiseLevels(stride, levels)

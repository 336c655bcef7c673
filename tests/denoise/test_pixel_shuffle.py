"""Pixel-shuffle downsampling: split and merge, and the stride chosen from the noise levels it reads."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_synth.effects import EffectContext, apply_effects, parse_effect
from denoise.noise_level import LUMA_GAIN, LUMA_WEIGHTS
from denoise.pixel_shuffle import (
    JPEG_STRIDE,
    MIN_CORRELATED_NOISE_STD,
    MIN_NOISE_STD,
    STRONG_LEVEL_RATIO,
    SUB_CHROMA_DEFICIT_RATIO,
    choose_stride,
    merge_std,
    pd_merge,
    pd_split,
    shuffled,
    stride_for,
    unshuffled,
)


@pytest.mark.parametrize("shape", [(12, 18, 3), (13, 17, 3), (9, 10)])
@pytest.mark.parametrize("stride", [1, 2, 3, 4])
def test_split_then_merge_gives_the_image_back(shape, stride, rng):
    img = rng.random(shape).astype(np.float32)
    parts = pd_split(img, stride)
    assert len(parts) == stride * stride
    # Sub-image (r, c) holds pixel (r + stride * i, c + stride * j) at (i, j): by the definition, pixel by pixel.
    r, c = divmod(len(parts) - 1, stride)
    last = parts[-1]
    for i in range(last.shape[0]):
        for j in range(last.shape[1]):
            assert np.array_equal(last[i, j], img[r + stride * i, c + stride * j])
    assert np.array_equal(pd_merge(parts, stride, img.shape), img)


def test_merge_refuses_parts_that_do_not_fit(rng):
    parts = pd_split(rng.random((8, 8, 3)), 2)
    with pytest.raises(ValueError, match="need 4"):
        pd_merge(parts[:3], 2, (8, 8, 3))
    with pytest.raises(ValueError, match="expected"):
        pd_merge(parts, 2, (10, 8, 3))


def _smooth_scene(rng, h=160, w=160):
    """Large flat patches of random grey levels in [0.25, 0.75] (no clipping for noise of std < 0.08)."""
    levels = rng.uniform(0.25, 0.75, size=(h // 40 + 1, w // 40 + 1, 3))
    return np.repeat(np.repeat(levels, 40, axis=0), 40, axis=1)[:h, :w].astype(np.float32)


def _bayer(img, seed):
    eff = parse_effect({"type": "bayer_noise", "gain": 0.01, "read_sigma_8bit": 5.0}, key="noise", path=None)
    return apply_effects(img, (eff,), seed=seed, ctx=EffectContext("v", np.eye(3)))


def test_white_noise_reads_alike_on_photos_and_sub_images_and_gets_no_stride(rng):
    scenes = [_smooth_scene(rng) + rng.normal(0, 0.05, (160, 160, 3)).astype(np.float32) for _ in range(3)]
    read = choose_stride(scenes)
    assert read.stride == 1 and set(read.level_by_stride) == {1, 2}
    # The PCA estimator on 160 px of white noise: within a few percent of the truth, photo and sub-images.
    assert read.level_by_stride[1] == pytest.approx(0.05, rel=0.05)
    assert read.level_by_stride[2] == pytest.approx(0.05, rel=0.05)


def test_demosaiced_noise_reads_low_on_the_photos_and_gets_stride_two(rng):
    scenes = [_smooth_scene(rng) for _ in range(3)]
    read = choose_stride([_bayer(s, k) for k, s in enumerate(scenes)])
    # Bilinear demosaicing: a pixel shares sensor sites with its neighbours 1 and 2 pixels away, none 3
    # away; the estimator sees the photos' noise as content, the sub-images' as noise.
    assert read.stride == 2
    assert read.level_by_stride[1] < 0.5 * read.level_by_stride[2]
    assert set(read.level_by_stride) == {1, 2, 3}  # stride 3 read, and found to hold no more noise


def test_noise_correlated_over_three_pixels_gets_stride_three(rng):
    # Each pixel the mean of 3 x 3 independent samples: correlated with every pixel 1 or 2 away (in each
    # axis), independent of those 3 away. Stride 2's sub-images keep a correlation, stride 3's do not.
    scenes = [_smooth_scene(rng) for _ in range(3)]
    noisy = []
    for s in scenes:
        w = rng.normal(0, 0.15, (162, 162, 3))
        n = sum(w[i:i + 160, j:j + 160] for i in range(3) for j in range(3)) / 9.0
        noisy.append(s + n.astype(np.float32))
    assert choose_stride(noisy).stride == 3


def test_weak_or_unreadable_noise_gets_no_stride(rng):
    scenes = [_smooth_scene(rng) for _ in range(3)]
    faint = [s + 0.1 * (_bayer(np.full_like(s, 0.5), k) - 0.5) for k, s in enumerate(scenes)]  # ~1.3/255
    assert choose_stride(faint).stride == 1
    assert choose_stride([rng.random((40, 200, 3))]).stride == 1  # stride-4 sub-images under 16 px: not read
    many = [_bayer(s, k) for k, s in enumerate(scenes * 3)]
    assert choose_stride(many).stride == 2  # nine photos, six of them read


def test_demosaiced_noise_that_reads_faint_gets_stride_two_by_its_ratio(rng):
    """Demosaiced noise read under `MIN_NOISE_STD` in the sub-images (as on the temple ring, whose clipped black
    background the PCA estimator reads) still reads far lower on the photos: `STRONG_LEVEL_RATIO` decides.
    White noise at the same level reads alike on both and keeps stride 1."""
    scenes = [_smooth_scene(rng) for _ in range(3)]
    weak = [s + 0.45 * (_bayer(np.full_like(s, 0.5), k) - 0.5) for k, s in enumerate(scenes)]
    read = choose_stride(weak)
    assert MIN_CORRELATED_NOISE_STD <= read.level_by_stride[2] < MIN_NOISE_STD  # the case the ratio decides
    assert read.level_by_stride[1] < STRONG_LEVEL_RATIO * read.level_by_stride[2] and read.stride == 2
    white = [s + rng.normal(0, read.level_by_stride[2], s.shape).astype(np.float32) for s in scenes]
    assert choose_stride(white).stride == 1


def _jpeg(img, quality, seed):
    eff = parse_effect({"type": "jpeg", "quality": quality}, key="noise", path=None)
    return apply_effects(img, (eff,), seed=seed, ctx=EffectContext("v", np.eye(3)))


def test_a_jpegs_noise_reads_on_its_luma_and_gets_no_stride(rng):
    """JPEG's 4:2:0 chroma subsampling leaves the colour directions of a patch without fine noise: the colour
    patches read under 1/255, and the stride rule read that as correlated noise (stride 2, at a third of the
    level). The luma keeps the noise, white: stride 1 at the luma's level."""
    scenes = [_smooth_scene(rng) for _ in range(3)]
    noisy = [np.clip(s + rng.normal(0, 0.1, s.shape), 0, 1).astype(np.float32) for s in scenes]
    read = choose_stride([_jpeg(x, 90, k) for k, x in enumerate(noisy)])
    assert read.level_by_stride[1] < 0.1 * 0.1  # the colour patches: 0.5-1.0/255 of 25.5 on three seeds
    # The luma after the round trip: 102-105 % of the noise's std on three seeds of this scene (the
    # quantisation adds a little); 10 % bounds it.
    assert read.stride == 1 and read.luma_level == pytest.approx(0.1, rel=0.1)
    assert set(read.level_by_stride) == {1} and read.record()["noise_level_luma_255"] == pytest.approx(25.5, rel=0.1)
    png = choose_stride(noisy)  # the same noise without the JPEG: read on the colour patches, as before
    assert png.stride == 1 and png.luma_level is None and set(png.level_by_stride) == {1, 2}
    clean = choose_stride([_jpeg(s, 90, k) for k, s in enumerate(scenes)])
    assert clean.stride == 1 and clean.luma_level is None


def test_demosaiced_noise_saved_as_a_jpeg_gets_stride_two_at_the_luma_level(rng):
    """A camera's photo: demosaiced noise (correlated between neighbouring pixels), then a JPEG (its colour
    differences subsampled). The luma reads a JPEG's noise as before but its eigenvalues spread, so it is not
    taken for white; the sub-images' colour patches read the subsampled colour differences, not the noise, so
    their levels do not choose the stride: `JPEG_STRIDE`, at the level the sub-images' luma reads. Before,
    such photos got stride 1 at the luma's 0.67 of the level (and on DTU scan24 stride 3 at a colour level a
    third of it)."""
    scenes = [_smooth_scene(rng) for _ in range(3)]
    noisy = [_jpeg(_bayer(s, k), 90, k) for k, s in enumerate(scenes)]
    read = choose_stride(noisy)
    assert read.stride == JPEG_STRIDE == 2 and read.noise_model == "luma"
    # The truth: the std of the luma of the noise the photos hold (noisy - clean), RGB-equivalent. The
    # reading is 97.5-98.9 % of it on three seeds; 10 % bounds it.
    true = np.median([np.std((np.asarray(x, np.float64) - s) @ np.asarray(LUMA_WEIGHTS)) / LUMA_GAIN
                      for x, s in zip(noisy, scenes, strict=True)])
    assert read.luma_level == pytest.approx(true, rel=0.1)
    assert read.level_by_stride[2] < 0.5 * read.luma_level  # the sub-images' colour patches under-read it
    png = choose_stride([_bayer(s, k) for k, s in enumerate(scenes)])  # as PNGs: the colour rule, as before
    assert png.stride == 2 and png.luma_level is None and png.noise_model == "auto"
    white = choose_stride([_jpeg(np.clip(s + rng.normal(0, true, s.shape), 0, 1).astype(np.float32), 90, k)
                           for k, s in enumerate(scenes)])  # white noise at that level: stride 1, on the luma
    assert white.stride == 1 and white.noise_model == "luma" and white.luma_level == pytest.approx(true, rel=0.1)


def test_a_cameras_jpeg_whose_noise_the_colour_patches_cannot_show_gets_a_hint(rng):
    """At JPEG quality 80 the sub-images' colour patches read the same demosaiced noise at 1.4/255, under the
    floor a clean photo's texture reads up to: the stride stays 1 at the colour level (nothing is changed),
    but `luma_hint_level` records the level the stride-2 sub-images' luma reads, which the report turns into
    `--pd-stride 2 --noise-model luma`. Clean JPEGs of these flat scenes, the noise as PNGs (found) and white
    noise as JPEGs (read on the luma) get no hint."""
    scenes = [_smooth_scene(rng) for _ in range(3)]
    q90 = choose_stride([_jpeg(_bayer(s, k), 90, k) for k, s in enumerate(scenes)])
    q80 = choose_stride([_jpeg(_bayer(s, k), 80, k) for k, s in enumerate(scenes)])
    assert q80.stride == 1 and q80.noise_model == "auto" and q80.luma_level is None
    assert q80.level_by_stride[2] < MIN_CORRELATED_NOISE_STD  # why it is not found
    # The same noise's level as quality 90 finds it (14.9/255 both; the JPEG's quality barely moves the luma).
    assert q80.luma_hint_level == pytest.approx(q90.luma_level, rel=0.1)
    assert "--pd-stride 2 --noise-model luma" in q80.hint()
    assert q80.record()["noise_level_luma_hint_255"] == pytest.approx(255 * q80.luma_hint_level, abs=0.01)
    for other in (choose_stride([_jpeg(s, 80, k) for k, s in enumerate(scenes)]),
                  choose_stride([_bayer(s, k) for k, s in enumerate(scenes)]), q90,
                  choose_stride([_jpeg(np.clip(s + rng.normal(0, 0.06, s.shape), 0, 1).astype(np.float32), 80, k)
                                 for k, s in enumerate(scenes)])):
        assert other.luma_hint_level is None and other.hint() is None


def test_a_given_stride_on_a_cameras_jpeg_hints_at_the_luma_noise_model(rng):
    """`--pd-stride 2` given without `--noise-model luma`: the denoisers would read each photo's level on its
    colour patches, which a JPEG's chroma subsampling has smoothed (1.4/255 at quality 80 against 14.9 in the
    luma), and remove little. `stride_for` reads both on the given stride's sub-images and hints at the luma
    model; not for the same noise as PNGs (the colour patches read it), nor where the caller gives a noise
    model (`hint=False`), nor for stride 1 or 0."""
    scenes = [_smooth_scene(rng) for _ in range(3)]
    for quality in (80, 90):
        photos = [_jpeg(_bayer(s, k), quality, k) for k, s in enumerate(scenes)]
        given = stride_for(photos, 2)
        assert given.stride == 2 and given.luma_hint_level is not None
        assert given.level_by_stride[2] < SUB_CHROMA_DEFICIT_RATIO * given.luma_hint_level
        # The level the luma reads is the one `choose_stride` finds at quality 90 (or hints at, at 80).
        found = choose_stride(photos)
        assert given.luma_hint_level == pytest.approx(found.luma_level or found.luma_hint_level, rel=1e-6)
        assert "--pd-stride 2 was given" in given.hint() and "--noise-model luma" in given.hint()
        assert given.record()["noise_level_luma_hint_255"] == pytest.approx(255 * given.luma_hint_level, abs=0.01)
        unread = stride_for(photos, 2, hint=False)
        assert unread.hint() is None and unread.level_by_stride == {}
        assert stride_for(photos, 1).hint() is None
    png = stride_for([_bayer(s, k) for k, s in enumerate(scenes)], 2)
    assert png.hint() is None and png.level_by_stride[2] > MIN_CORRELATED_NOISE_STD


def test_shuffled_and_unshuffled_are_inverse_over_a_list(rng):
    images = [rng.random((10, 14, 3)), rng.random((9, 11, 3))]
    parts = shuffled(images, 3)
    assert len(parts) == 18
    back = unshuffled(parts, 3, [im.shape for im in images])
    assert all(np.array_equal(a, b) for a, b in zip(back, images, strict=True))
    with pytest.raises(ValueError, match="17 sub-images"):
        unshuffled(parts[:17], 3, [im.shape for im in images])


def test_a_photos_std_is_put_back_together_from_its_sub_images():
    assert merge_std([0.1, 0.2, 0.3, 0.2], 2, (6, 8, 3)) == pytest.approx(0.2)
    full = torch.arange(3 * 5 * 7, dtype=torch.float32).reshape(3, 5, 7)
    parts = [torch.from_numpy(p).permute(2, 0, 1) for p in pd_split(full.permute(1, 2, 0).numpy(), 2)]
    parts[3] = 0.5  # a number among maps: a constant map
    merged = merge_std(parts, 2, (5, 7, 3))
    expected = full.clone()
    expected[:, 1::2, 1::2] = 0.5
    assert merged.dtype == torch.float32 and torch.equal(merged, expected)


def test_noise_levels_log_line_lists_the_levels_read():
    from denoise.pixel_shuffle import NoiseLevels

    assert NoiseLevels(2, {1: 10 / 255, 2: 20 / 255}).levels_255() == "1: 10.0, 2: 20.0"
    assert NoiseLevels(1, {}).levels_255() == "not measured"
    assert NoiseLevels(1, {1: 1 / 255}, 24 / 255).levels_255() == "1: 1.0; luma: 24.0"


def test_the_luma_noise_model_reads_each_sub_image_on_its_luma(rng):
    """The denoisers read each image's level themselves: on the sub-images of demosaiced noise saved as a JPEG
    ``"auto"`` reads their colour patches (their colour differences are subsampled, but less than a JPEG's
    photo's: they are not found chroma-subsampled one by one), ``"luma"``, which `choose_stride` gives the set,
    reads the luma for R2R and N2V's fusion alike."""
    from denoise.inference import fusion_noise_sigma
    from denoise.noise_level import estimate_noise_sigma_pca, luma_noise_sigma
    from denoise.self_supervised import r2r_noise_std

    scene = _smooth_scene(rng)
    noisy = _jpeg(_bayer(scene, 0), 90, 0)
    under = []
    for sub, clean in zip(pd_split(noisy, JPEG_STRIDE), pd_split(scene, JPEG_STRIDE), strict=True):
        # Each sub-image holds one site of the colour filter pattern: its own level. The luma reads 92-102 %
        # of it (three seeds, four sub-images each); 15 % bounds it.
        true = float(np.std((np.asarray(sub, np.float64) - clean) @ np.asarray(LUMA_WEIGHTS)) / LUMA_GAIN)
        luma = r2r_noise_std(sub, noise_model="luma")
        assert luma == luma_noise_sigma(sub, exclude_clipped=True) == pytest.approx(true, rel=0.15)
        assert fusion_noise_sigma(sub, torch.as_tensor(sub), noise_model="luma") == luma
        auto = r2r_noise_std(sub)  # "auto": the colour patches (a per-pixel map where shot noise dominates)
        under.append(float(auto.median() if isinstance(auto, torch.Tensor) else auto) / luma)
    assert np.median(under) < 0.5  # 0.28-0.29 of the luma's level on three seeds
    gray = noisy.mean(axis=2)
    assert r2r_noise_std(gray, noise_model="luma") == estimate_noise_sigma_pca(gray, exclude_clipped=True)

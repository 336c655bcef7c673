"""Pixel-shuffle downsampling: split and merge, the noise's correlation, the stride chosen from it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_synth.effects import EffectContext, apply_effects, parse_effect
from denoise.pixel_shuffle import (
    MIN_NOISE_STD,
    RESIDUAL_CORRELATION,
    choose_stride,
    merge_std,
    noise_lag_correlation,
    pd_merge,
    pd_split,
    shuffled,
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


def test_white_noise_reads_uncorrelated(rng):
    img = _smooth_scene(rng) + rng.normal(0, 0.05, (160, 160, 3)).astype(np.float32)
    rho = noise_lag_correlation(img)
    # 2 x ~7,000 flat pixel pairs per lag and channel: a mean square's relative s.e. is sqrt(2 / 7000) = 1.7 %,
    # the ratio of two about 2.4 %; 0.1 is about four of them.
    assert np.abs(rho[:, :4]).max() < 0.1
    assert rho[:, 4] == pytest.approx(0.05, rel=0.05)  # the noise std, from the far differences


def test_two_tap_noise_has_the_correlation_of_its_filter(rng):
    # n = (w + w shifted by one column) / sqrt 2: correlation 0.5 between horizontal neighbours, 0 beyond
    # and 0 vertically, so the mean over the two axes is 0.25 at lag 1 and 0 at lags 2-4.
    w = rng.normal(0, 0.05, (160, 161, 3))
    n = (w[:, 1:] + w[:, :-1]) / np.sqrt(2.0)
    rho = noise_lag_correlation(_smooth_scene(rng) + n.astype(np.float32)).mean(axis=0)
    assert rho[0] == pytest.approx(0.25, abs=0.06)
    assert np.abs(rho[1:4]).max() < 0.06


def _bayer(img, seed):
    eff = parse_effect({"type": "bayer_noise", "gain": 0.01, "read_sigma_8bit": 5.0}, key="noise", path=None)
    return apply_effects(img, (eff,), seed=seed, ctx=EffectContext("v", np.eye(3)))


def test_the_stride_decorrelates_demosaiced_noise_and_is_one_for_white_noise_or_none(rng):
    scenes = [_smooth_scene(rng) for _ in range(3)]
    # Bilinear demosaicing: a pixel shares sensor sites with its neighbours 1 and 2 pixels away, none 3 away;
    # the pixels 2 away share fewer (true correlation 0.13 along rows, under RESIDUAL_CORRELATION): stride 2.
    demosaiced = choose_stride([_bayer(s, k) for k, s in enumerate(scenes)])
    assert demosaiced.stride == 2
    assert demosaiced.lag_correlation[1] > 0.4
    assert demosaiced.lag_correlation[2] < RESIDUAL_CORRELATION and abs(demosaiced.lag_correlation[3]) < 0.1
    white = choose_stride([s + rng.normal(0, 0.05, s.shape).astype(np.float32) for s in scenes])
    assert white.stride == 1 and white.lag_correlation[1] < 0.1
    # Correlated but faint: under the noise floor, no stride.
    faint = [s + (0.5 * MIN_NOISE_STD) * (_bayer(np.full_like(s, 0.5), k) - 0.5) / 0.05
             for k, s in enumerate(scenes)]
    assert choose_stride(faint).stride == 1


def test_shuffled_and_unshuffled_are_inverse_over_a_list(rng):
    images = [rng.random((10, 14, 3)), rng.random((9, 11, 3))]
    parts = shuffled(images, 3)
    assert len(parts) == 18
    back = unshuffled(parts, 3, [im.shape for im in images])
    assert all(np.array_equal(a, b) for a, b in zip(back, images, strict=True))
    with pytest.raises(ValueError, match="17 sub-images"):
        unshuffled(parts[:17], 3, [im.shape for im in images])


def test_photos_too_small_to_measure_get_no_stride(rng):
    assert choose_stride([rng.random((10, 40, 3))]).stride == 1


def test_a_photos_std_is_put_back_together_from_its_sub_images():
    assert merge_std([0.1, 0.2, 0.3, 0.2], 2, (6, 8, 3)) == pytest.approx(0.2)
    full = torch.arange(3 * 5 * 7, dtype=torch.float32).reshape(3, 5, 7)
    parts = [torch.from_numpy(p).permute(2, 0, 1) for p in pd_split(full.permute(1, 2, 0).numpy(), 2)]
    parts[3] = 0.5  # a number among maps: a constant map
    merged = merge_std(parts, 2, (5, 7, 3))
    expected = full.clone()
    expected[:, 1::2, 1::2] = 0.5
    assert torch.equal(merged, expected)

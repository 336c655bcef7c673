"""`denoise.detail.noisy_detail_target` against a slow explicit convolution, and its properties."""

from __future__ import annotations

import numpy as np
import pytest

from denoise.detail import NoisyDetail, gaussian_kernel_size, noisy_detail_target, noisy_detail_weight


def _reference(denoised: np.ndarray, noisy: np.ndarray, weight: float, sigma: float) -> np.ndarray:
    """The same target by a direct double loop: a normalised sampled Gaussian of radius
    `gaussian_kernel_size(sigma) // 2`, mirrored borders without repeating the edge pixel (numpy 'reflect',
    OpenCV's BORDER_REFLECT_101), float64 throughout."""
    r = gaussian_kernel_size(sigma) // 2
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-x ** 2 / (2 * sigma ** 2))
    g /= g.sum()
    k2 = np.outer(g, g)
    res = noisy.astype(np.float64) - denoised.astype(np.float64)
    pad = np.pad(res, ((r, r), (r, r), (0, 0)), mode="reflect")
    h, w, _ = res.shape
    blur = np.zeros_like(res)
    for i in range(h):
        for j in range(w):
            blur[i, j] = np.tensordot(k2, pad[i:i + 2 * r + 1, j:j + 2 * r + 1], axes=([0, 1], [0, 1]))
    return np.clip(denoised + weight * (res - blur), 0.0, 1.0)


@pytest.mark.parametrize("sigma", [0.7, 1.0, 1.6])
def test_matches_the_explicit_convolution(sigma):
    rng = np.random.default_rng(1)
    den = rng.uniform(0.2, 0.8, (13, 17, 3)).astype(np.float32)
    noisy = np.clip(den + rng.normal(0, 0.1, den.shape), 0, 1).astype(np.float32)
    got = noisy_detail_target(den, noisy, NoisyDetail(0.4, sigma))
    assert got.dtype == np.float32 and got.shape == den.shape
    # float32 arithmetic on values in [0, 1] (OpenCV's float32 blur): 1e-5 is ~100 float32 ulps of 1.
    np.testing.assert_allclose(got, _reference(den, noisy, 0.4, sigma), atol=1e-5)


def test_weight_zero_is_the_denoised_photo_and_smooth_residuals_add_nothing():
    rng = np.random.default_rng(2)
    den = rng.uniform(0.2, 0.8, (16, 16, 3)).astype(np.float32)
    noisy = np.clip(den + rng.normal(0, 0.1, den.shape), 0, 1).astype(np.float32)
    np.testing.assert_array_equal(noisy_detail_target(den, noisy, NoisyDetail(0.0)), den)
    # A constant residual has no high band: the target is the denoised photo whatever the weight.
    np.testing.assert_allclose(noisy_detail_target(den, den + 0.05, NoisyDetail(1.0)), den, atol=1e-6)
    # Away from clipping the added band is linear in the weight.
    a, b = (noisy_detail_target(den, noisy, NoisyDetail(w)) - den for w in (0.25, 0.5))
    full = noisy_detail_target(den, noisy, NoisyDetail(1.0))
    inside = (full > 0) & (full < 1)
    np.testing.assert_allclose(2 * a[inside], b[inside], atol=2e-6)


def test_the_views_mean_target_takes_back_the_texture_the_denoiser_removed():
    """Many noisy views of one textured surface, a denoiser that blurs it: the mean of the views' targets
    (what a splat fitting them all converges to, where it fits them equally) is closer to the clean
    surface than the denoised photo, and the added noise is what averages away."""
    import cv2

    rng = np.random.default_rng(3)
    clean = np.clip(0.5 + 0.2 * rng.standard_normal((48, 48, 3)), 0, 1).astype(np.float32)
    den = cv2.GaussianBlur(clean, (7, 7), 1.5)  # the texture removed, the same in every view
    views = [np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1).astype(np.float32) for _ in range(24)]
    detail = NoisyDetail(0.5)
    mean_target = np.mean([noisy_detail_target(den, v, detail) for v in views], axis=0)
    single_target = noisy_detail_target(den, views[0], detail)

    def mse(x):
        return float(((x - clean) ** 2).mean())

    assert mse(mean_target) < 0.6 * mse(den)
    # One view's target carries w^2 of the noise's high band, about 0.25 * 0.1^2 * 0.76 = 1.9e-3 (0.76: the
    # share of white noise's variance above a 1-px Gaussian); the mean of 24 carries 1/24 of it.
    assert mse(single_target) - mse(mean_target) > 1.2e-3


def test_the_weight_is_scaled_down_above_the_reference_noise():
    d = NoisyDetail(0.2)  # reference 25/255
    assert noisy_detail_weight(d, 10 / 255) == 0.2 and noisy_detail_weight(d, 25 / 255) == pytest.approx(0.2)
    assert noisy_detail_weight(d, 50 / 255) == pytest.approx(0.1)
    assert noisy_detail_weight(d, None) == 0.2 and noisy_detail_weight(d, 0.0) == 0.2  # unknown: as set
    assert noisy_detail_weight(NoisyDetail(0.2, reference_std=None), 50 / 255) == 0.2
    rng = np.random.default_rng(4)
    den = rng.uniform(0.2, 0.8, (16, 16, 3)).astype(np.float32)
    noisy = np.clip(den + rng.normal(0, 0.2, den.shape), 0, 1).astype(np.float32)
    np.testing.assert_array_equal(noisy_detail_target(den, noisy, d, 50 / 255),
                                  noisy_detail_target(den, noisy, NoisyDetail(0.1, reference_std=None)))


def test_bad_arguments_are_refused():
    a = np.zeros((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match="shape|must both"):
        noisy_detail_target(a, a[:3], NoisyDetail(0.5))
    with pytest.raises(ValueError, match="weight"):
        NoisyDetail(1.5)
    with pytest.raises(ValueError, match="sigma_px"):
        NoisyDetail(0.5, 0.0)
    with pytest.raises(ValueError, match="reference_std"):
        NoisyDetail(0.5, 1.0, 0.0)


def test_no_band_in_a_dark_clipped_region():
    """A black background under noise clipped at 0 (the temple ring's): its band is rectified noise, so the
    target there is the denoised photo; elsewhere the band is added as without the rule."""
    from denoise.clipping import dark_clipped_mask

    rng = np.random.default_rng(3)
    den = np.full((40, 60, 3), 0.5, np.float32)
    den[:, :30] = 0.0  # the left half is black
    noisy = np.clip(den + rng.normal(0, 25 / 255, den.shape), 0, 1).astype(np.float32)
    dark = dark_clipped_mask(noisy)
    assert dark[:, :20].all() and not dark[:, 40:].any()  # the black half, not the grey one
    skip = noisy_detail_target(den, noisy, NoisyDetail(0.5))
    keep = noisy_detail_target(den, noisy, NoisyDetail(0.5, skip_dark_clipped=False))
    np.testing.assert_array_equal(skip[dark], den[dark])
    np.testing.assert_array_equal(skip[~dark], keep[~dark])
    assert keep[:, :20].mean() > 1e-3  # without the rule the black half gets the rectified noise's positive part

"""`denoise.clipping`: the clipped-noise mean against Monte Carlo, its inverse, the side test, and the
R2R / Neighbor2Neighbor outputs it corrects."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from denoise.clipping import clipped_mean, clipped_sides, clipped_variance, undo_clipping_bias


@pytest.mark.parametrize(("low", "high"), [(True, True), (True, False), (False, True)])
def test_clipped_mean_matches_monte_carlo(low, high):
    # 400k draws per value: the Monte-Carlo mean's std is sigma / sqrt(4e5) < 2e-4; tolerance 1e-3.
    rng = np.random.default_rng(0)
    x = np.array([-0.05, 0.0, 0.02, 0.1, 0.5, 0.93, 1.0, 1.04])
    sigma = 0.1
    draws = x[:, None] + sigma * rng.standard_normal((len(x), 400_000))
    clipped = np.clip(draws, 0.0 if low else -np.inf, 1.0 if high else np.inf)
    got = clipped_mean(torch.tensor(x), sigma, low=low, high=high).numpy()
    np.testing.assert_allclose(got, clipped.mean(axis=1), atol=1e-3)


@pytest.mark.parametrize(("low", "high"), [(True, True), (True, False), (False, True)])
def test_clipped_variance_matches_monte_carlo(low, high):
    # 400k draws per value: the sample variance's relative std is sqrt(2 / 4e5) ~ 0.2 % for Gaussian draws
    # (more for the clipped ones, whose kurtosis is higher); tolerance 1.5 % of the value.
    rng = np.random.default_rng(1)
    x = np.array([-0.05, 0.0, 0.02, 0.1, 0.5, 0.93, 1.0, 1.04])
    for sigma in (0.05, 0.2):
        draws = x[:, None] + sigma * rng.standard_normal((len(x), 400_000))
        clipped = np.clip(draws, 0.0 if low else -np.inf, 1.0 if high else np.inf)
        got = clipped_variance(torch.tensor(x), sigma, low=low, high=high).numpy()
        np.testing.assert_allclose(got, clipped.var(axis=1), rtol=0.015, atol=1e-7)
    # Black, clipped below: (1/2 - 1/(2 pi)) sigma^2; far from both bounds: sigma^2.
    assert abs(float(clipped_variance(torch.zeros(1, dtype=torch.float64), 0.1, high=False)) / 0.01
               - (0.5 - 0.5 / np.pi)) < 1e-9
    assert abs(float(clipped_variance(torch.full((1,), 0.5, dtype=torch.float64), 0.01)) / 1e-4 - 1) < 1e-9


def test_undo_inverts_the_clipped_mean_with_a_number_or_a_map():
    x = torch.linspace(0.0, 1.0, 201, dtype=torch.float64)
    for sigma in (0.1, 0.02 + 0.2 * x):  # a number, and a per-pixel map
        for low, high in ((True, True), (True, False), (False, True)):
            back = undo_clipping_bias(clipped_mean(x, sigma, low=low, high=high), sigma, low=low, high=high)
            torch.testing.assert_close(back, x, atol=1e-7, rtol=0)
    # Not clipped on either side: nothing to undo (clamped only).
    torch.testing.assert_close(undo_clipping_bias(x * 1.1 - 0.05, 0.1, low=False, high=False),
                               (x * 1.1 - 0.05).clamp(0, 1))


def test_undo_moves_a_clipped_black_level_back_to_black():
    # sigma 25/255 on black: the clipped photo's mean is 0.4 sigma (10/255); undone: 0 (clamped from below).
    sigma = 25 / 255
    grey = clipped_mean(torch.zeros(1, dtype=torch.float64), sigma)
    assert abs(float(grey) - sigma / np.sqrt(2 * np.pi)) < 1e-6
    assert float(undo_clipping_bias(grey, sigma)) < 1e-6
    assert float(undo_clipping_bias(torch.tensor([0.001], dtype=torch.float64), sigma)) == 0.0  # below f(0)


def test_clipped_sides():
    rng = np.random.default_rng(1)
    x = np.full((64, 64, 3), 0.5)
    assert clipped_sides(np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1)) == (False, False)
    dark = x.copy()
    dark[:16] = 0.0
    assert clipped_sides(np.clip(dark + 0.1 * rng.standard_normal(x.shape), 0, 1)) == (True, False)
    bright = x.copy()
    bright[:, :16] = 1.0
    assert clipped_sides(np.clip(bright + 0.1 * rng.standard_normal(x.shape), 0, 1)) == (False, True)


@pytest.mark.parametrize("method", ["r2r", "neighbor2neighbor"])
def test_the_non_blind_methods_undo_the_bias_where_the_photo_is_clipped(rng, method):
    # denoise_with_method with and without undo_clipping: the corrected output is the inverse applied to
    # the uncorrected one, with the std of r2r_noise_std, on the clipped side only (black here).
    from denoise.n2v import N2VConfig
    from denoise.self_supervised import denoise_with_method, r2r_noise_std, train_self_supervised
    from denoise.unet import UNetConfig

    clean = np.full((40, 40, 3), 0.6, np.float32)
    clean[:, :16] = 0.0  # a black band: a third of the photo clipped at 0
    noisy = [np.clip(clean + 0.1 * rng.standard_normal(clean.shape), 0, 1).astype(np.float32) for _ in range(2)]
    cfg = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=3, batch_size=2, patch_px=16, method=method)
    model = train_self_supervised(noisy, cfg, seed=0)
    raw = denoise_with_method(model, noisy, cfg, passes=2, seed=1, undo_clipping=False)
    fixed = denoise_with_method(model, noisy, cfg, passes=2, seed=1)
    for img, r, f in zip(noisy, raw, fixed, strict=True):
        assert clipped_sides(img) == (True, False)
        sigma = torch.as_tensor(r2r_noise_std(img), dtype=torch.float32)
        ref = undo_clipping_bias(torch.from_numpy(r).permute(2, 0, 1), sigma, low=True, high=False)
        np.testing.assert_allclose(f, ref.permute(1, 2, 0).numpy(), atol=1e-6)
        assert np.mean(f[:, :16]) < np.mean(r[:, :16])  # the black band got darker


def _photo(clean: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(clean + sigma * rng.standard_normal(clean.shape), 0.0, 1.0).astype(np.float32)


def test_dark_clipped_fraction_reads_black_regions_not_dark_texture():
    from denoise.clipping import dark_clipped_fraction

    sigma = 25 / 255
    half_black = np.zeros((96, 128, 3), np.float32)
    half_black[:, 64:] = 0.6
    # Half the pixels are black: all of them read as dark clipped but a border about the blur's width
    # (4 px of 64) where the neighbourhood reaches the bright half.
    assert 0.44 < dark_clipped_fraction(_photo(half_black, sigma, 0)) <= 0.5
    # Values one or two noise std above black put 16 % / 2 % of their values on 0: not a black region.
    for level in (sigma, 2 * sigma):
        assert dark_clipped_fraction(_photo(np.full((64, 64, 3), level, np.float32), sigma, 1)) == 0.0
    # Blown highlights (clipped at 1) are not dark.
    assert dark_clipped_fraction(_photo(np.ones((64, 64, 3), np.float32), sigma, 2)) == 0.0
    # Gray photos (H, W) as well as colour. All black: the local share of zeros is about 0.5 everywhere;
    # over 20 noise seeds a few pixels' neighbourhoods fell under 0.4 (fraction 0.947-1.0).
    assert dark_clipped_fraction(_photo(np.zeros((32, 32), np.float32), sigma, 3)) > 0.9


def test_choose_objective_switches_to_neighbor2neighbor_on_black_backgrounds():
    from denoise.self_supervised import MAX_DARK_CLIPPED_FOR_R2R, choose_objective
    from mvgeo.common.errors import InputError

    sigma = 25 / 255
    scene = np.full((64, 96, 3), 0.5, np.float32)
    assert choose_objective([_photo(scene, sigma, k) for k in range(3)]).method == "r2r"
    black_background = scene.copy()
    black_background[:, :60] = 0.0  # 62 % of the area black, as the temple ring's photos
    choice = choose_objective([_photo(black_background, sigma, k) for k in range(3)])
    assert choice.method == "neighbor2neighbor" and choice.dark_clipped_fraction > MAX_DARK_CLIPPED_FOR_R2R
    # The rule is the mean over the photos against the threshold: one black-background photo among three
    # plain ones reads about 0.15.
    mixed = [_photo(black_background, sigma, 4)] + [_photo(scene, sigma, k) for k in range(5, 8)]
    assert choose_objective(mixed).method == "r2r" and 0.1 < choose_objective(mixed).dark_clipped_fraction < 0.2
    small = scene.copy()
    small[:, :10] = 0.0  # 10 of 96 columns black: about 7.5 % once the blur's border is off
    assert choose_objective([_photo(small, sigma, 5)]).method == "r2r"
    with pytest.raises(InputError):
        choose_objective([])

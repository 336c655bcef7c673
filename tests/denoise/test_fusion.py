"""Blind-spot / observation fusion: a scipy reference, limiting cases, and a Bayes-optimal case."""

import numpy as np
import pytest
import scipy.ndimage as ndi
import torch

from denoise.fusion import fuse_with_observation
from mvgeo.common.errors import ShapeError


def _reference(mu, y, sigma, window):
    """Slow, obvious version: per channel, scipy Gaussian (reflect) of the squared residual."""
    out = np.empty_like(mu)
    for b in range(mu.shape[0]):
        for c in range(mu.shape[1]):
            r = y[b, c] - mu[b, c]
            m2 = ndi.gaussian_filter(r * r, window, mode="reflect", truncate=4.0)
            vp = np.maximum(m2 - sigma**2, 0.0)
            gain = np.where(vp + sigma**2 > 0, vp / np.maximum(vp + sigma**2, 1e-300), 1.0)
            out[b, c] = mu[b, c] + gain * r
    return out


def test_matches_scipy_reference(rng):
    mu = rng.uniform(0, 1, (2, 3, 23, 31))
    y = mu + rng.normal(0, 0.2, mu.shape)
    got = fuse_with_observation(torch.from_numpy(mu), torch.from_numpy(y), noise_sigma=0.1, window_sigma_px=1.5)
    # float64 both sides, same taps and border: only summation order differs.
    np.testing.assert_allclose(got.numpy(), _reference(mu, y, 0.1, 1.5), rtol=0, atol=1e-12)


def test_limits(rng):
    mu = torch.from_numpy(rng.uniform(0, 1, (1, 3, 16, 16)))
    y = mu + torch.from_numpy(rng.normal(0, 0.1, (1, 3, 16, 16)))
    # No noise: the observation is exact and is returned.
    torch.testing.assert_close(fuse_with_observation(mu, y, noise_sigma=0.0), y, rtol=0, atol=1e-15)
    # Noise far above the residual: the prior wins everywhere.
    torch.testing.assert_close(fuse_with_observation(mu, y, noise_sigma=10.0), mu, rtol=0, atol=0)
    # Prediction equal to the observation: nothing to blend.
    torch.testing.assert_close(fuse_with_observation(y, y, noise_sigma=0.1), y, rtol=0, atol=0)


def test_recovers_texture_the_prior_missed(rng):
    # Clean = smooth part (known to the "network") + strong texture it could not predict.
    # The fused estimate must beat both mu and y (the MMSE blend of two noisy estimates).
    h = w = 96
    smooth = ndi.gaussian_filter(rng.uniform(0, 1, (h, w)), 6)
    texture = 0.3 * rng.standard_normal((h, w))
    clean = smooth + texture
    sigma = 0.1
    y = clean + sigma * rng.standard_normal((h, w))
    t = lambda a: torch.from_numpy(a)[None, None]  # noqa: E731
    out = fuse_with_observation(t(smooth), t(y), noise_sigma=sigma)[0, 0].numpy()
    mse = lambda a: float(np.mean((a - clean) ** 2))  # noqa: E731
    # Bayes gain 0.09 / (0.09 + 0.01) = 0.9: expected MSE ~ 0.9 * sigma^2 = 0.009 vs y's 0.01 and
    # mu's 0.09; the local variance estimate costs a little, so require a 5 % win over y.
    assert mse(out) < 0.95 * mse(y) and mse(out) < 0.2 * mse(smooth)


def test_per_image_sigma_broadcasts(rng):
    mu = torch.from_numpy(rng.uniform(0, 1, (2, 3, 12, 12)))
    y = mu + 0.05
    sig = torch.tensor([0.0, 10.0], dtype=torch.float64).reshape(2, 1, 1, 1)
    out = fuse_with_observation(mu, y, noise_sigma=sig)
    torch.testing.assert_close(out[0], y[0], rtol=0, atol=1e-15)
    torch.testing.assert_close(out[1], mu[1], rtol=0, atol=0)


def test_bad_input():
    with pytest.raises(ShapeError):
        fuse_with_observation(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 9), noise_sigma=0.1)
    with pytest.raises(ValueError, match="window_sigma_px"):
        fuse_with_observation(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8), noise_sigma=0.1, window_sigma_px=0)

"""Image losses against scikit-image / scipy references and known cases."""

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage.metrics import structural_similarity

from denoise.filters import gaussian_blur, pad_symmetric
from denoise.losses import (
    charbonnier,
    chroma_loss,
    gradient_loss,
    low_frequency_loss,
    rgb_to_ycbcr,
    total_variation,
)
from mvgeo.common.errors import ShapeError
from mvgeo.image_metrics import ssim, ssim_map


def _pair(rng, h=37, w=45, dtype=np.float64):
    """A textured image and a noisy, slightly shifted copy (SSIM well inside (0, 1))."""
    yy, xx = np.mgrid[0:h, 0:w]
    base = 0.5 + 0.3 * np.sin(xx[..., None] * np.array([0.3, 0.5, 0.2]) + yy[..., None] * 0.2)
    a = np.clip(base + 0.05 * rng.standard_normal((h, w, 3)), 0, 1)
    b = np.clip(np.roll(base, 1, axis=1) + 0.1 * rng.standard_normal((h, w, 3)), 0, 1)
    return a.astype(dtype), b.astype(dtype)


def _t(a):
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]


def _skimage_ssim(a, b):
    return structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=-1)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ssim_matches_skimage(rng, dtype):
    # Same formula and window; differences are summation order only. float64 agrees to ~1e-12;
    # float32 moments (E[x^2] - E[x]^2 cancellation) give ~1e-6, so 1e-4 (the contract) is loose for both.
    a, b = _pair(rng, dtype=dtype)
    ours = ssim(_t(a), _t(b)).item()
    ref = _skimage_ssim(a, b)
    assert 0.2 < ref < 0.95  # a non-trivial case
    assert abs(ours - ref) < (1e-10 if dtype == np.float64 else 1e-4)


def test_ssim_batch_and_reduction(rng):
    a1, b1 = _pair(rng)
    a2, b2 = _pair(rng)
    x = torch.cat([_t(a1), _t(a2)])
    y = torch.cat([_t(b1), _t(b2)])
    per = ssim(x, y, reduction="none")
    assert per.shape == (2,)
    # 1e-10: float64, same arithmetic as the skimage path up to summation order.
    assert abs(per[0].item() - _skimage_ssim(a1, b1)) < 1e-10
    assert abs(per[1].item() - _skimage_ssim(a2, b2)) < 1e-10
    assert abs(ssim(x, y).item() - per.mean().item()) < 1e-12


def test_ssim_full_map_matches_skimage_reflect(rng):
    # border="reflect" is skimage's full S map (scipy 'reflect' padding); float64 -> 1e-10.
    a, b = _pair(rng, h=20, w=23)
    _, s_ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                     data_range=1.0, channel_axis=-1, full=True)
    s = ssim_map(_t(a), _t(b), border="reflect")[0].numpy().transpose(1, 2, 0)
    assert s.shape == s_ref.shape
    np.testing.assert_allclose(s, s_ref, atol=1e-10)


def test_ssim_identical_is_one_and_gradcheck(rng):
    a, b = _pair(rng, h=14, w=13)
    x = _t(a)
    # Identical images: every local term is exactly (2m^2+c1)(2v+c2)/((2m^2+c1)(2v+c2)) = 1 up to rounding.
    assert abs(ssim(x, x).item() - 1.0) < 1e-12
    xr = x[:, :1, :13, :12].clone().requires_grad_(True)
    yr = _t(b)[:, :1, :13, :12].clone()
    assert torch.autograd.gradcheck(lambda t: ssim(t, yr), (xr,))
    assert torch.autograd.gradcheck(lambda t: ssim(t, yr, border="reflect"), (xr,))


def test_ssim_too_small_raises():
    x = torch.zeros(1, 3, 8, 8)
    with pytest.raises(ShapeError):
        ssim(x, x)
    # reflect border works on images smaller than the window.
    assert abs(ssim(x + 0.3, x + 0.3, border="reflect").item() - 1.0) < 1e-6
    with pytest.raises(ShapeError):
        ssim(x, torch.zeros(1, 3, 8, 9))


def test_gaussian_blur_matches_scipy(rng):
    a = rng.random((1, 2, 17, 9))
    for sigma in (0.7, 2.0, 3.0):  # 3.0: the 25-tap window is wider than W=9 -> repeated mirroring
        ours = gaussian_blur(torch.from_numpy(a), sigma=sigma).numpy()
        ref = ndimage.gaussian_filter(a, sigma=(0, 0, sigma, sigma), mode="reflect")
        np.testing.assert_allclose(ours, ref, atol=1e-12)  # float64, same taps


def test_pad_symmetric_is_numpy_symmetric(rng):
    a = rng.random((1, 1, 4, 3))
    for r in (1, 3, 7):
        ref = np.pad(a, ((0, 0), (0, 0), (r, r), (r, r)), mode="symmetric")
        np.testing.assert_array_equal(pad_symmetric(torch.from_numpy(a), r).numpy(), ref)


def test_charbonnier_known_values():
    x = torch.zeros(1, 1, 2, 2, dtype=torch.float64)
    y = torch.tensor([[[[0.0, 3.0], [4.0, -3.0]]]], dtype=torch.float64)
    eps = 4.0
    expected = (4.0 + 5.0 + np.sqrt(32.0) + 5.0) / 4
    assert abs(charbonnier(x, y, eps=eps).item() - expected) < 1e-12
    assert abs(charbonnier(x, x, eps=1e-3).item() - 1e-3) < 1e-15
    xr = torch.randn(1, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    yr = torch.randn(1, 2, 3, 3, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda t: charbonnier(t, yr, eps=0.1), (xr,))


def test_gradient_loss_known_values():
    h, w = 5, 6
    ramp = torch.arange(w, dtype=torch.float64).expand(1, 1, h, w).clone()
    # A constant offset has the same gradients.
    assert gradient_loss(ramp, ramp + 7.0).item() == 0.0
    # ramp vs flat: dx differs by 1 everywhere, dy by 0 -> 0.5 * (1 + 0).
    assert abs(gradient_loss(ramp, torch.zeros_like(ramp)).item() - 0.5) < 1e-12
    xr = torch.randn(1, 2, 4, 5, dtype=torch.float64, requires_grad=True)
    yr = torch.randn(1, 2, 4, 5, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda t: gradient_loss(t, yr), (xr,))


def test_ycbcr_and_chroma(rng):
    grey = torch.full((1, 3, 2, 2), 0.37, dtype=torch.float64)
    ycc = rgb_to_ycbcr(grey)
    # Grey -> Y = value, Cb = Cr = 0.5 (rows of the BT.601 matrix: 1, 0, 0).
    np.testing.assert_allclose(ycc[0, :, 0, 0].numpy(), [0.37, 0.5, 0.5], atol=1e-6)
    # Reference: skimage's studio-range conversion undone ((Y-16)/219, (C-128)/224 + 0.5).
    from skimage.color import rgb2ycbcr
    a = rng.random((4, 5, 3))
    ref = rgb2ycbcr(a)
    ref = np.stack([(ref[..., 0] - 16) / 219, (ref[..., 1] - 128) / 224 + 0.5, (ref[..., 2] - 128) / 224 + 0.5], -1)
    ours = rgb_to_ycbcr(_t(a))[0].numpy().transpose(1, 2, 0)
    np.testing.assert_allclose(ours, ref, atol=1e-5)  # skimage's matrix is rounded to ~6 digits
    # Chroma ignores a grey (luminance-only) change, not a colour change.
    x = _t(a)
    assert abs(chroma_loss(x, x * 0 + 0.2, eps=1e-6).item() - chroma_loss(x, x * 0 + 0.7, eps=1e-6).item()) < 1e-9
    assert chroma_loss(x, (x + 0.1).clamp(0, 1), eps=1e-6).item() < 1e-2
    assert chroma_loss(x, x[:, [1, 2, 0]], eps=1e-6).item() > 0.05


def test_total_variation_known_values():
    checker = (torch.arange(4).reshape(4, 1) + torch.arange(4).reshape(1, 4)) % 2
    x = checker.to(torch.float64).reshape(1, 1, 4, 4)
    assert total_variation(x).item() == 2.0  # every forward difference is +-1
    assert total_variation(torch.full((1, 3, 5, 5), 0.4)).item() == 0.0
    xr = torch.randn(1, 1, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: total_variation(t, eps=0.1), (xr,))


def test_low_frequency_loss_ignores_zero_mean_noise(rng):
    h, w = 64, 64
    clean = torch.full((1, 3, h, w), 0.5, dtype=torch.float64)
    noisy = clean + 0.1 * torch.from_numpy(rng.standard_normal((1, 3, h, w)))
    # Blurring with sigma 2 averages ~50 effective pixels: noise std 0.1 -> ~0.014 after blur,
    # vs 0.1 before; the low-frequency term sees a small fraction of the raw Charbonnier distance.
    assert low_frequency_loss(noisy, clean).item() < 0.25 * charbonnier(noisy, clean).item()
    assert low_frequency_loss(clean + 0.1, clean).item() == pytest.approx(0.1, abs=1e-5)

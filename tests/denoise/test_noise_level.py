"""Noise-level estimates: accuracy on white noise, robustness to edges."""

import numpy as np
import pytest
import torch

from denoise.images import images_to_tensors
from denoise.model import load_checkpoint, save_checkpoint
from denoise.n2v import N2VConfig, new_model
from denoise.noise_level import (
    LUMA_WEIGHTS,
    WHITE_LUMA_MAX_SPREAD,
    NoiseCurve,
    _patches,
    _surround_level,
    estimate_noise_curve,
    estimate_noise_sigma,
    estimate_noise_sigma_clipped,
    estimate_noise_sigma_pca,
    estimate_noise_sigma_robust,
    fit_clipped_noise_sigma,
    luma_noise_sigma,
    luma_noise_spread,
)
from denoise.unet import UNetConfig


def test_robust_estimate_on_white_noise(rng):
    # 256x256x3 Gaussian samples on a flat grey: the median of ~65k |I*M| values has a relative
    # standard error well below 1 %, so 3 % is a safe bound; the constant is exact (6 * 0.6745).
    for sigma in (0.02, 0.1):
        img = 0.5 + sigma * rng.standard_normal((256, 256, 3))
        assert abs(estimate_noise_sigma_robust(img) / sigma - 1) < 0.03
        assert abs(estimate_noise_sigma(img) / sigma - 1) < 0.03
    gray = 0.5 + 0.05 * rng.standard_normal((128, 128))
    assert abs(estimate_noise_sigma_robust(gray) / 0.05 - 1) < 0.05  # 16k samples
    assert estimate_noise_sigma_robust(np.zeros((2, 5, 3))) == 0.0


def test_robust_estimate_ignores_edges(rng):
    # A checkerboard of 16 px squares: every edge inflates the mean-based estimate; the median
    # mostly sees the noise (77 % of the pixels' 3x3 windows lie off the edges).
    yy, xx = np.mgrid[:128, :128]
    clean = np.repeat((((yy // 16) + (xx // 16)) % 2)[..., None] * 0.6 + 0.2, 3, axis=2)
    img = clean + 0.03 * rng.standard_normal(clean.shape)
    robust, mean_based = estimate_noise_sigma_robust(img), estimate_noise_sigma(img)
    # Measured 0.0347 mean-based (+16 %) vs 0.0301 robust (+0.4 %); the bounds sit between.
    assert mean_based > 1.1 * 0.03  # the bias the robust estimate removes
    assert abs(robust / 0.03 - 1) < 0.05, robust


def test_blind_spot_flag_in_checkpoint(tmp_path, rng):
    img = rng.random((16, 16, 3)).astype(np.float32)
    model = new_model(N2VConfig(unet=UNetConfig(width=2, depth=1)), images_to_tensors([img]), seed=0)
    assert model.blind_spot
    model.blind_spot = False
    save_checkpoint(tmp_path / "m.pt", model)
    assert not load_checkpoint(tmp_path / "m.pt").blind_spot


def _ramp(h=200, w=200):
    yy, xx = np.mgrid[:h, :w] / max(h, w)
    return np.stack([xx, yy, 0.5 * xx + 0.3 * yy], 2) * 0.9 + 0.05  # in [0.05, 0.95]


def test_noise_curve_poisson_gaussian(rng):
    # Poisson-Gaussian noise on smooth ramps (the 3x3 mask cancels them): the fit must find
    # the gain and the floor. 120k samples over 8 bins: the per-bin median variance has a
    # ~2 % relative error; 15 % on the gain and a 2x band on the (small, 4e-4) floor hold.
    a, s = 0.01, 5 / 255
    img = np.clip(a * rng.poisson(_ramp() / a) + s * rng.standard_normal((200, 200, 3)), 0, 1)
    curve = estimate_noise_curve(img)
    assert curve.gain == pytest.approx(a, rel=0.15)
    assert 0.5 * s**2 < curve.floor < 2 * s**2
    sig = curve.sigma_at(torch.tensor([0.0, 0.5, 2.0], dtype=torch.float64))
    torch.testing.assert_close(sig, torch.tensor([curve.floor, 0.5 * curve.gain + curve.floor,
                                                  curve.gain + curve.floor], dtype=torch.float64).sqrt())


def test_noise_curve_gaussian_is_flat(rng):
    # Additive Gaussian noise: the gain is (near) zero and the floor is sigma^2. Clipped pixels
    # are dropped, so the clipping at 0 / 1 (ramp ends 0.05 / 0.95 = 1.7 sigma) biases little.
    img = np.clip(_ramp() + 0.03 * rng.standard_normal((200, 200, 3)), 0, 1)
    curve = estimate_noise_curve(img)
    assert curve.gain < 0.05 * 0.03**2 / 0.5  # its contribution at mid-grey: < 5 % of the variance
    assert curve.floor == pytest.approx(0.03**2, rel=0.1)
    assert estimate_noise_curve(np.zeros((2, 8))) == NoiseCurve(0.0, 0.0)
    assert estimate_noise_curve(np.ones((20, 20, 3))) == NoiseCurve(0.0, 0.0)  # all clipped, no noise
    # Too small to bin (30x30 px: 676 patches < 4 * 8 * 75): one flat level, the PCA estimate.
    small = 0.5 + 0.05 * rng.standard_normal((30, 30, 3))
    curve = estimate_noise_curve(small)
    assert curve.gain == 0.0 and curve.floor == pytest.approx(estimate_noise_sigma_pca(small) ** 2, rel=1e-12)
    with pytest.raises(ValueError, match="bins"):
        estimate_noise_curve(img, bins=1)


def test_patches_match_loops(rng):
    from denoise.noise_level import _patches
    img = rng.random((7, 9, 3))
    got = _patches(img, 3)
    ref = np.array([[img[y + dy, x + dx, c] for c in range(3) for dy in range(3) for dx in range(3)]
                    for y in range(5) for x in range(7)])
    np.testing.assert_array_equal(got, ref)
    assert _patches(img, 8) is None
    thinned = _patches(rng.random((100, 100)), 5, max_patches=1000)  # 96^2 positions, stride 4
    assert thinned.shape == (24 * 24, 25)


def test_pca_estimate_ignores_channel_correlated_texture(rng):
    # Pixel-scale luminance texture (the same in all channels, std 0.05) plus white noise 0.03
    # per channel. The Laplacian estimators see both; the PCA tail sees the noise only.
    # 60k 75-D patches: eigenvalue spread ~ sqrt(75/60k) = 4 %, so 8 % bounds the estimate.
    tex = 0.05 * rng.standard_normal((200, 200, 1))
    img = 0.5 + tex * np.array([1.0, 0.9, 0.8]) + 0.03 * rng.standard_normal((200, 200, 3))
    assert abs(estimate_noise_sigma_pca(img) / 0.03 - 1) < 0.08
    assert estimate_noise_sigma_robust(img) > 1.3 * 0.03  # the bias the PCA estimate removes
    for sigma in (0.02, 0.1):  # pure white noise
        assert abs(estimate_noise_sigma_pca(0.5 + sigma * rng.standard_normal((128, 128, 3))) / sigma - 1) < 0.08
    assert abs(estimate_noise_sigma_pca(0.5 + 0.05 * rng.standard_normal((128, 128))) / 0.05 - 1) < 0.08
    assert estimate_noise_sigma_pca(np.zeros((4, 40, 3))) == 0.0
    assert estimate_noise_sigma_pca(np.full((40, 40, 3), 0.3)) == 0.0
    with pytest.raises(ValueError, match="patch_px"):
        estimate_noise_sigma_pca(img, patch_px=1)


def test_pca_estimate_without_the_clipped_patches(rng):
    # A dark half (true value 0.02) and a mid-grey half, white noise sigma 0.1, clipped to [0, 1] as a
    # camera writes it: in the dark half most values clip at 0 and hold far less noise. The estimate
    # over all patches is pulled low; the unclipped patches (the grey half, 100x200 px, ~19k 75-D
    # patches: eigenvalue spread ~ sqrt(75/19k) = 6 %) give sigma within 8 %.
    sigma = 0.1
    clean = np.full((200, 200, 3), 0.5)
    clean[:100] = 0.02
    img = np.clip(clean + sigma * rng.standard_normal(clean.shape), 0.0, 1.0)
    assert estimate_noise_sigma_pca(img) < 0.85 * sigma
    assert abs(estimate_noise_sigma_pca(img, exclude_clipped=True) / sigma - 1) < 0.08
    # Too few unclipped patches (all but a 5-row strip clipped: 196 of the 300 needed): all patches count.
    almost_black = np.clip(np.where(np.arange(200)[:, None, None] < 195, 0.0, 0.5)
                           + sigma * rng.standard_normal(clean.shape), 0.0, 1.0)
    assert estimate_noise_sigma_pca(almost_black, exclude_clipped=True) == estimate_noise_sigma_pca(almost_black)
    # Unclipped images: the option changes nothing.
    grey = 0.5 + 0.05 * rng.standard_normal((64, 64, 3))
    assert estimate_noise_sigma_pca(grey, exclude_clipped=True) == estimate_noise_sigma_pca(grey)


def _dark_photo(rng, sigma: float, size: int = 200) -> np.ndarray:
    """A shaded, lightly textured disc (28 % of the area, clean values 0.07-0.6) on black, with white noise
    `sigma`, clipped to [0, 1] and stored in 8 bits, as a camera writes a dark scene."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    disc = (xx - 0.55) ** 2 + (yy - 0.5) ** 2 < 0.3**2
    shade = 0.1 + 0.5 * xx[..., None] * np.array([1.0, 0.8, 0.6]) + 0.03 * rng.standard_normal((size, size, 1))
    clean = np.where(disc[..., None], shade, 0.0)
    return np.round(np.clip(clean + sigma * rng.standard_normal(clean.shape), 0.0, 1.0) * 255) / 255


@pytest.mark.parametrize("seed", [0, 1])
def test_clipped_fit_reads_the_noise_of_a_dark_photo(seed):
    # ~40k 3x3x3 patches in 8 bins of ~5k 27-D samples: each bin's PCA tail is within a few percent; the fit
    # read 1-2 % low over seeds 0-2 (a clipped value is not Gaussian; the bins span levels). Bound: 5 %.
    rng = np.random.default_rng(seed)
    for sigma in (0.05, 0.1, 0.2):
        img = _dark_photo(rng, sigma)
        fit = fit_clipped_noise_sigma(img)
        assert abs(fit / sigma - 1) < 0.05, (sigma, fit)
        both = estimate_noise_sigma_clipped(img)
        assert both == max(fit, estimate_noise_sigma_pca(img, exclude_clipped=True))
        assert abs(both / sigma - 1) < 0.05
    # The defect it removes: at sigma 0.2 the unclipped patches are mid-tones whose noise stayed inside
    # [0, 1]: truncated, about 0.7 sigma.
    img = _dark_photo(rng, 0.2)
    assert estimate_noise_sigma_pca(img, exclude_clipped=True) < 0.8 * 0.2


def test_clipped_fit_on_unclipped_and_clean_images(rng):
    # No clipping: the clipped model is the Gaussian, the fit reads plain white noise.
    grey = 0.5 + 0.05 * rng.standard_normal((128, 128, 3))
    assert abs(fit_clipped_noise_sigma(grey) / 0.05 - 1) < 0.05
    # A clean dark photo: next to nothing (the lower end of the search, 0.5/255).
    clean = np.where(np.arange(64)[:, None, None] < 40, 0.0, 0.4) * np.ones((64, 64, 3))
    assert fit_clipped_noise_sigma(clean) <= 1.0 / 255
    assert fit_clipped_noise_sigma(np.zeros((2, 2, 3))) == 0.0  # smaller than a patch
    assert fit_clipped_noise_sigma(np.zeros((3, 3, 3))) == 0.0  # one patch


def test_surround_level_matches_a_loop(rng):
    # Each patch's ring mean (the square of side patch + 2 ring around it, minus the patch; borders
    # reflected as OpenCV's BORDER_REFLECT: ...cba|abc...), on `_patches`' grid and in its order.
    img = rng.uniform(size=(23, 31, 3))
    for patch_px, max_patches in ((3, 10**6), (5, 40)):
        got = _surround_level(img, patch_px, max_patches, ring_px=2)
        g = np.pad(img.mean(axis=2), 2, mode="symmetric")  # the ring reaches 2 px past the image
        n = (23 - patch_px + 1) * (31 - patch_px + 1)
        step = max(1, int(np.ceil(np.sqrt(n / max_patches))))
        want = []
        for i in range(0, 23 - patch_px + 1, step):
            for j in range(0, 31 - patch_px + 1, step):
                outer = g[i:i + patch_px + 4, j:j + patch_px + 4]  # padded coordinates: patch at (i + 2, j + 2)
                inner = outer[2:2 + patch_px, 2:2 + patch_px]
                want.append((outer.sum() - inner.sum()) / (outer.size - inner.size))
        assert len(got) == len(want) == len(_patches(img, patch_px, max_patches))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_a_jpegs_noise_is_read_on_its_luma(rng):
    """After a JPEG round trip (4:2:0 chroma) the colour patches hold no fine noise and read about 1/255 of
    white noise of 25.5/255; the luma keeps it. `estimate_noise_sigma_clipped` and R2R's level read the luma
    there, and read as before where the colour patches see the noise or where there is none."""
    from data_synth.effects import EffectContext, apply_effects, parse_effect
    from denoise.self_supervised import r2r_noise_std

    eff = parse_effect({"type": "jpeg", "quality": 90}, key="noise", path=None)
    base = 0.25 + 0.5 * _ramp(160, 160)  # in [0.27, 0.73]: little clipped
    noisy = np.clip(base + rng.normal(0, 0.1, base.shape), 0, 1).astype(np.float32)
    jpeg = apply_effects(noisy, (eff,), seed=0, ctx=EffectContext("v", np.eye(3)))
    assert estimate_noise_sigma_pca(jpeg, exclude_clipped=True) < 0.1 * 0.1  # 0.6-1.3/255 on four seeds
    # 101-103 % of the std on four seeds (JPEG's quantisation adds a little); 10 % bounds it.
    assert estimate_noise_sigma_clipped(jpeg) == pytest.approx(0.1, rel=0.1)
    assert float(r2r_noise_std(jpeg)) == estimate_noise_sigma_clipped(jpeg)
    # White noise as a PNG holds it: the luma reads as the colour patches (within the estimator's few %),
    # and the level is the colour one, to the bit.
    assert luma_noise_sigma(noisy) == pytest.approx(estimate_noise_sigma_pca(noisy), rel=0.05)
    colour = max(estimate_noise_sigma_pca(noisy, exclude_clipped=True), fit_clipped_noise_sigma(noisy))
    assert estimate_noise_sigma_clipped(noisy) == colour
    clean = apply_effects(base.astype(np.float32), (eff,), seed=0, ctx=EffectContext("v", np.eye(3)))
    assert estimate_noise_sigma_clipped(clean) < 2 / 255  # a clean JPEG stays clean


def _spread_reference(img: np.ndarray, p: int = 5) -> float:
    """`luma_noise_spread` by its definition: every p x p luma patch inside (0, 1), their covariance with numpy,
    the fifth smallest eigenvalue over the smallest."""
    y = np.asarray(img, np.float64) @ np.asarray(LUMA_WEIGHTS)
    rows = [y[i:i + p, j:j + p].reshape(-1) for i in range(y.shape[0] - p + 1) for j in range(y.shape[1] - p + 1)]
    rows = np.array([r for r in rows if r.min() > 0 and r.max() < 1])
    eig = np.sort(np.linalg.eigvalsh(np.cov(rows.T, bias=True)))
    return float(eig[4] / eig[0])


def test_the_lumas_eigenvalue_spread_tells_white_noise_from_demosaiced_noise(rng):
    """White noise adds the same variance to every direction of the patch space: the smallest eigenvalues are
    alike. Demosaiced noise has little power at the finest scales: they spread."""
    from data_synth.effects import EffectContext, apply_effects, parse_effect

    base = (0.25 + 0.5 * _ramp(96, 96)).astype(np.float32)
    white = np.clip(base + rng.normal(0, 0.05, base.shape), 0, 1).astype(np.float32)
    eff = parse_effect({"type": "bayer_noise", "gain": 0.01, "read_sigma_8bit": 5.0}, key="noise", path=None)
    demosaiced = apply_effects(base, (eff,), seed=0, ctx=EffectContext("v", np.eye(3)))
    # All 8464 patches of a 96 px image (under max_patches): the same value as the definition, to round-off.
    for img in (white, demosaiced):
        assert luma_noise_spread(img) == pytest.approx(_spread_reference(img), rel=1e-9)
    # White 1.03-1.05 on four seeds (the sample eigenvalues' own spread from 8464 patches); demosaiced 9.8-10.8.
    assert luma_noise_spread(white) < WHITE_LUMA_MAX_SPREAD < luma_noise_spread(demosaiced)
    assert np.isnan(luma_noise_spread(base[:4, :4]))  # smaller than a patch


def test_a_gray_photo_read_as_rgb_reads_its_noise_as_the_gray_photo(rng):
    """A gray photo read as RGB (`mvgeo.common.imageio.read_image` replicates its one channel) holds the same
    noise in every channel: the estimators that assume independent channels read it on the one channel. (Its
    colour patches span a third of the patch space, so their PCA tail read 0 and the N2V fusion, at a noise
    std of 0, returned the noisy photo; the luma, which holds the whole noise, read it 1.5x too high.)"""
    from denoise.inference import fusion_noise_sigma
    from denoise.noise_level import chroma_subsampled_noise_sigma, constant_noise_sigma_luma

    gray = np.clip(0.1 + 0.8 * _ramp(120, 120)[..., 0] + rng.normal(0, 0.1, (120, 120)), 0, 1).astype(np.float32)
    rgb = np.repeat(gray[..., None], 3, axis=2)
    for estimate in (estimate_noise_sigma, estimate_noise_sigma_pca, fit_clipped_noise_sigma,
                     estimate_noise_sigma_clipped, constant_noise_sigma_luma, luma_noise_sigma):
        assert estimate(rgb) == pytest.approx(estimate(gray) if estimate is not luma_noise_sigma
                                              else estimate_noise_sigma_pca(gray), rel=1e-9), estimate.__name__
    assert estimate_noise_sigma_pca(rgb, exclude_clipped=True) == pytest.approx(0.1, rel=0.05)
    assert estimate_noise_curve(rgb) == estimate_noise_curve(gray)
    assert chroma_subsampled_noise_sigma(rgb) is None
    x = torch.from_numpy(rgb.transpose(2, 0, 1).copy())[None]
    assert float(fusion_noise_sigma(rgb, x, noise_model="constant")) == pytest.approx(0.1, rel=0.05)


def test_the_lumas_unclipped_patches_leave_out_blown_white(rng):
    """A pixel at 1 in all three channels has luma 1 (the weights sum to 1), so its patches are clipped in the
    luma. (In float64 the weights' dot product with (1, 1, 1) is 0.9999999999999999: a blown highlight counted as
    unclipped and its noise-free patches pulled the level down: 0.072 for 0.1 here, 22.2/255 for 25/255 on a
    DTU scan24 photo.)"""
    base = 0.25 + 0.5 * _ramp(120, 120)
    base[:, :60] = 1.5  # blown white: every channel clipped at 1
    noisy = np.clip(base + rng.normal(0, 0.1, base.shape), 0, 1)
    assert ((noisy >= 1).all(axis=2)).mean() > 0.45
    rest = noisy[:, 60:]
    assert luma_noise_sigma(noisy, exclude_clipped=True) == pytest.approx(
        luma_noise_sigma(rest, exclude_clipped=True), rel=0.03)
    assert luma_noise_sigma(noisy, exclude_clipped=True) == pytest.approx(0.1, rel=0.05)

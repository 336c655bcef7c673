"""Inference: tiling without seams, K-pass averaging, and hard inputs."""

import numpy as np
import pytest
import torch

from denoise.fusion import fuse_with_observation
from denoise.inference import (
    denoise_images,
    denoise_tensor,
    dihedral,
    fusion_noise_sigma,
    predict_tiled,
    tile_starts,
)
from denoise.masking import mask_pixels
from denoise.n2v import N2VConfig, new_model, train_n2v
from denoise.noise_level import estimate_noise_curve, estimate_noise_sigma_pca
from denoise.unet import UNetConfig
from mvgeo.common.errors import InputError
from tests.denoise._synth import add_noise, psnr, smooth_scene

TINY = N2VConfig(unet=UNetConfig(width=4, depth=4), steps=30, batch_size=2, patch_px=32)


@pytest.fixture(scope="module")
def trained():
    rng = np.random.default_rng(0)
    imgs = [add_noise(rng, smooth_scene(rng, 40, 40), 0.1) for _ in range(2)]
    with torch.random.fork_rng():
        torch.set_num_threads(1)
        return train_n2v(imgs, TINY, seed=0)


def test_tile_starts_cover():
    for n, core in [(10, 4), (8, 4), (3, 4), (101, 32)]:
        starts = tile_starts(n, core)
        covered = np.zeros(n, bool)
        for s in starts:
            covered[s : s + core] = True
        assert covered.all() and starts[-1] + min(core, n) == n


def test_tiled_equals_whole_image_no_seams(trained, rng):
    # Whole-image prediction vs 32 px cores with 48 px of context, on an image larger than a core and its
    # margins (128 px), so that it is tiled. The 4-level UNet's receptive field is larger than 48 px and its
    # max-pooling grid sits differently in each tile, so tiling is not exact; but the influence of far
    # pixels decays fast: differences stay under one 8-bit step (3.9e-3; measured 2.3e-3 at most, 1.1e-5 on
    # average, against a noise level of 0.1) and are not concentrated on tile borders.
    h, w = 200, 180
    assert min(h, w) > 32 + 2 * 48
    x = torch.from_numpy(add_noise(rng, smooth_scene(rng, h, w), 0.1).transpose(2, 0, 1).copy())[None]
    with torch.no_grad():
        whole = trained.apply(x)
        tiled = predict_tiled(trained, x, tile_px=32, margin_px=48)
    diff = (whole - tiled).abs()
    assert diff.max().item() < 1 / 255 and diff.mean().item() < 1e-4
    # Seam check: the output's jump across each tile border is no larger than elsewhere.
    dx = (tiled[..., :, 1:] - tiled[..., :, :-1]).abs().mean(dim=(0, 1, 2))
    borders = [s - 1 for s in tile_starts(w, 32)[1:]]
    others = [i for i in range(w - 1) if i not in borders]
    assert dx[borders].mean() < 1.5 * dx[others].mean()
    # An image that fits in a core and its margins is processed whole: exactly the network's output.
    with torch.no_grad():
        exact = predict_tiled(trained, x[..., :100, :90], tile_px=32, margin_px=100)
        whole = trained.apply(x[..., :100, :90])
    torch.testing.assert_close(exact, whole, rtol=0, atol=1e-6)  # float32 conv re-ordering only


def test_passes_average_and_seed(trained, rng):
    img = add_noise(rng, smooth_scene(rng, 33, 35), 0.1)
    a = denoise_images(trained, [img], passes=3, seed=1, fuse=False)[0]
    b = denoise_images(trained, [img], passes=3, seed=1, fuse=False)[0]
    np.testing.assert_array_equal(a, b)
    # The K-pass result is the mean of the individual masked passes drawn from one generator.
    x = torch.from_numpy(img.transpose(2, 0, 1).copy())[None]
    gen = torch.Generator().manual_seed(1)
    singles = [denoise_tensor(trained, x, passes=1, generator=gen) for _ in range(3)]
    mean = torch.stack(singles).mean(0)[0].clamp(0, 1).numpy().transpose(1, 2, 0)
    np.testing.assert_allclose(a, mean, atol=1e-6)
    # Default for a round-1 (blind-spot) model: that mean fused with the observation.
    assert trained.blind_spot
    fused = denoise_images(trained, [img], passes=3, seed=1, noise_sigma=0.1)[0]
    ref = fuse_with_observation(torch.stack(singles).mean(0), x, noise_sigma=0.1)[0].clamp(0, 1)
    np.testing.assert_allclose(fused, ref.numpy().transpose(1, 2, 0), atol=1e-6)  # float32, same ops
    assert not np.allclose(fused, a, atol=1e-3)  # the fusion did something
    unmasked = denoise_images(trained, [img], passes=0)[0]
    assert unmasked.shape == img.shape and unmasked.dtype == np.float32


@pytest.mark.parametrize("shape", [(31, 17, 3), (5, 7, 3), (2, 2, 3), (20, 21), (20, 21, 1)])
def test_odd_small_and_gray_shapes(trained, rng, shape):
    img = rng.random(shape).astype(np.float32)
    out = denoise_images(trained, [img], passes=2)[0]
    assert out.shape == img.shape and np.isfinite(out).all()
    assert out.min() >= 0 and out.max() <= 1


def test_constant_image():
    # Training on a constant image: std is floored, loss is zero-ish, output stays the constant.
    const = np.full((40, 40, 3), 0.3, np.float32)
    model = train_n2v([const], TINY, seed=0)
    assert all(np.isfinite(model.history))
    out = denoise_images(model, [const], passes=2, clean_sigma=0.0)[0]  # bypass the clean-image gate
    # The centre-cancelling init predicts from the neighbours (all 0.3); 30 steps keep it there.
    np.testing.assert_allclose(out, 0.3, atol=0.02)


def test_saturated_regions(rng):
    # Clipped regions: the right third is over-exposed (1.0 before and after noise + clipping).
    clean = smooth_scene(rng, 48, 48)
    clean[:, 32:] = 1.0
    noisy = add_noise(rng, clean, 0.1)
    model = train_n2v([noisy], N2VConfig(unet=UNetConfig(width=8), steps=200, batch_size=4, patch_px=32), seed=0)
    out = denoise_images(model, [noisy], passes=2)[0]
    assert out.max() <= 1.0 and np.isfinite(out).all()
    # The clipped noise is one-sided (mean ~0.96 in the white area); stay close to white there.
    assert out[:, 36:].mean() > 0.93
    assert psnr(out, clean) > psnr(noisy, clean)


def test_no_noise_does_not_damage(rng):
    # sigma = 0: N2V trained on clean images predicts each pixel from its neighbours and
    # blurs edges (measured 23 dB vs the input). The noise-level gate must leave such
    # images untouched (up to clipping), while noisy images of the same scene are denoised.
    clean = [smooth_scene(rng, 64, 64) for _ in range(2)]
    model = train_n2v(clean, N2VConfig(unet=UNetConfig(width=4), steps=20, batch_size=2, patch_px=32), seed=0)
    out = denoise_images(model, clean, passes=2)
    for o, c in zip(out, clean, strict=True):
        np.testing.assert_array_equal(o, c)
    # 8-bit quantised clean images (sigma ~0.3/255) are also below the gate.
    q = [np.round(c * 255) / 255 for c in clean]
    assert all(np.array_equal(o, c.astype(np.float32)) for o, c in zip(denoise_images(model, q), q, strict=True))
    noisy = add_noise(rng, clean[0], 5 / 255)
    assert not np.array_equal(denoise_images(model, [noisy])[0], noisy)
    # Without the gate the image is processed.
    assert not np.array_equal(denoise_images(model, clean[:1], clean_sigma=0.0)[0], clean[0])


def test_noise_estimate(rng):
    # Immerkaer's estimator on a smooth scene: within 10% of the true sigma for white noise
    # (the scene's curvature adds < 0.1/255); clipping is avoided by the [0.1, 0.9] range.
    from denoise.noise_level import estimate_noise_sigma
    img = smooth_scene(rng, 96, 96)
    assert estimate_noise_sigma(img) < 0.2 / 255
    for sigma in (2 / 255, 10 / 255):
        noisy = (img + sigma * rng.standard_normal(img.shape)).astype(np.float32)
        assert estimate_noise_sigma(noisy) == pytest.approx(sigma, rel=0.1)


def test_untrained_model_is_centre_cancelling_and_errors(rng):
    model = new_model(TINY, [torch.rand(3, 8, 8)], seed=0)
    x = torch.rand(1, 3, 16, 16)
    y1 = model.apply(x)
    x2 = x.clone()
    x2[0, :, 8, 8] += 0.5
    y2 = model.apply(x2)
    # The centre pixel's own value does not reach its output through the linear path; only
    # through the (randomly initialised, small) convolutional features.
    assert (y2 - y1)[0, :, 8, 8].abs().max().item() < 0.25
    with pytest.raises(InputError):
        denoise_images(model, [np.full((4, 4, 3), np.inf, np.float32)])


def test_dihedral_transforms():
    x = torch.arange(12.0).reshape(1, 1, 3, 4)
    seen = set()
    for k in range(8):
        t = dihedral(x, k)
        torch.testing.assert_close(dihedral(t, k, inverse=True), x, rtol=0, atol=0)
        seen.add((tuple(t.shape), tuple(t.flatten().tolist())))
    assert len(seen) == 8  # all 8 symmetries of the square are distinct on a generic image
    torch.testing.assert_close(dihedral(x, 5), torch.rot90(torch.flip(x, dims=(-1,)), 1, dims=(-2, -1)))


def test_dihedral_ensemble_reference(trained, rng):
    # Slow, obvious version: pass k = transform, mask (same generator order), predict, undo.
    img = add_noise(rng, smooth_scene(rng, 30, 37), 0.1)  # non-square: rot90 changes the shape
    x = torch.from_numpy(img.transpose(2, 0, 1).copy())[None]
    got = denoise_tensor(trained, x, passes=5, generator=torch.Generator().manual_seed(3), dihedral_ensemble=True)
    gen = torch.Generator().manual_seed(3)
    ref = torch.zeros_like(x)
    for k in range(5):
        xt = torch.rot90(torch.flip(x, dims=(-1,)) if k >= 4 else x, k % 4, dims=(-2, -1))
        m = mask_pixels(xt, p=trained.mask_prob, replacement=trained.replacement, radius=trained.radius,
                        generator=gen).masked
        with torch.no_grad():
            p = torch.rot90(trained.apply(m), -(k % 4), dims=(-2, -1))
        ref += torch.flip(p, dims=(-1,)) if k >= 4 else p
    torch.testing.assert_close(got, ref / 5, rtol=0, atol=1e-6)  # float32, same ops in the same order
    out = denoise_images(trained, [img], passes=8, dihedral_ensemble=True)[0]
    assert out.shape == img.shape and np.isfinite(out).all()


def test_curve_noise_model_fuses_per_pixel(trained, rng):
    img = add_noise(rng, smooth_scene(rng, 40, 44), 0.1)
    x = torch.from_numpy(img.transpose(2, 0, 1).copy())[None]
    mu = denoise_tensor(trained, x, passes=2, generator=torch.Generator().manual_seed(0))
    curve = estimate_noise_curve(img)
    ref = fuse_with_observation(mu, x, noise_sigma=curve.sigma_at(mu))[0].clamp(0, 1).numpy().transpose(1, 2, 0)
    got = denoise_images(trained, [img], passes=2, seed=0, noise_model="curve")[0]
    np.testing.assert_allclose(got, ref, atol=1e-6)
    with pytest.raises(ValueError, match="noise_model"):
        denoise_images(trained, [img], noise_model="poisson")


def test_training_on_images_smaller_than_a_patch(rng):
    # 64 px patches requested, images of 12x9 and 20x21 px: training uses 9 px patches.
    imgs = [add_noise(rng, smooth_scene(rng, 12, 9), 0.1), add_noise(rng, smooth_scene(rng, 20, 21), 0.1)]
    model = train_n2v(imgs, N2VConfig(unet=UNetConfig(width=4), steps=5, batch_size=2, patch_px=64), seed=0)
    assert all(np.isfinite(model.history))
    out = denoise_images(model, imgs, passes=2)
    assert [o.shape for o in out] == [i.shape for i in imgs] and all(np.isfinite(o).all() for o in out)


def test_auto_noise_model_picks_per_image(rng):
    # Smooth ramps (no texture): Gaussian noise -> the constant PCA estimate; Poisson-Gaussian
    # (a = 0.01, s = 2/255: the shot term a * 0.5 is 30x the read variance) -> the curve.
    yy, xx = np.mgrid[:96, :96] / 96
    clean = np.stack([xx, yy, 0.5 * xx + 0.3 * yy], 2) * 0.8 + 0.1
    mu = torch.from_numpy(clean.transpose(2, 0, 1).copy())[None]
    gauss = clean + 0.05 * rng.standard_normal(clean.shape)
    assert fusion_noise_sigma(gauss, mu) == estimate_noise_sigma_pca(gauss, exclude_clipped=True)
    shot = 0.01 * rng.poisson(clean / 0.01) + 2 / 255 * rng.standard_normal(clean.shape)
    torch.testing.assert_close(fusion_noise_sigma(shot, mu), estimate_noise_curve(shot).sigma_at(mu))
    constant = fusion_noise_sigma(gauss, mu, noise_model="constant")
    assert constant == estimate_noise_sigma_pca(gauss, exclude_clipped=True)
    with pytest.raises(ValueError, match="noise_model"):
        fusion_noise_sigma(gauss, mu, noise_model="poisson")


def test_fusion_noise_sigma_reads_the_unclipped_noise(rng):
    # Half the image black, as the temple's background: clipping at 0 removes half the noise there, and an
    # estimate over all patches reads the level low; the fusion needs the std of the unclipped noise (25/255).
    yy, xx = np.mgrid[:128, :128] / 128
    clean = np.stack([xx, yy, 0.5 * xx + 0.3 * yy], 2) * 0.6 + 0.2
    clean[:, :64] = 0.0
    noisy = np.clip(clean + 25 / 255 * rng.standard_normal(clean.shape), 0, 1)
    mu = torch.from_numpy(clean.transpose(2, 0, 1).copy())[None]
    sigma = fusion_noise_sigma(noisy, mu, noise_model="constant")
    assert abs(sigma * 255 - 25) < 1.5  # 16k unclipped 5x5 patches: the estimate's spread is well under 1/255
    assert estimate_noise_sigma_pca(noisy) * 255 < 22  # what the fusion used before

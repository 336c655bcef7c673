"""`denoise.wiener`: the sliding-window DCT Wiener step against a per-block reference, and what it must do."""

from __future__ import annotations

import numpy as np
import pytest

from denoise.wiener import OPPONENT, WienerConfig, _strided_parts, dct_wiener, dct_wiener_gray


def _dct_matrix(n: int) -> np.ndarray:
    """Orthonormal DCT-II matrix: row k is the k-th basis vector."""
    k, x = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    D = np.sqrt(2.0 / n) * np.cos(np.pi * (2 * x + 1) * k / (2 * n))
    D[0] /= np.sqrt(2.0)
    return D


def _reference_gray(y: np.ndarray, p: np.ndarray, var: np.ndarray, block: int, step: int) -> np.ndarray:
    """One block at a time, with an explicit DCT matrix: the definition the fast path vectorises."""
    H, W = y.shape
    D = _dct_matrix(block)
    rows = sorted(set(range(0, H - block + 1, step)) | {H - block})
    cols = sorted(set(range(0, W - block + 1, step)) | {W - block})
    num, den = np.zeros((H, W)), np.zeros((H, W))
    for r in rows:
        for c in cols:
            sl = np.s_[r:r + block, c:c + block]
            v = max(float(np.mean(var[sl])), 1e-12)
            Y, P = D @ y[sl] @ D.T, D @ p[sl] @ D.T
            g = P ** 2 / (P ** 2 + v)
            w = 1.0 / (v * np.sum(g ** 2) + 1e-12 * v)
            num[sl] += w * (D.T @ (g * Y) @ D)
            den[sl] += w
    return num / den


@pytest.mark.parametrize("shape,block,step", [((23, 30), 8, 2), ((16, 19), 8, 3), ((12, 12), 4, 1), ((9, 14), 6, 6)])
def test_the_fast_path_matches_the_per_block_reference(shape, block, step):
    rng = np.random.default_rng(0)
    p = rng.random(shape)
    y = p + rng.normal(0, 0.1, shape)
    var = (0.05 + 0.1 * rng.random(shape)) ** 2  # per pixel: each block's mean
    cfg = WienerConfig(block_px=block, step_px=step, rows_per_chunk=2)  # several chunks
    for v in (var, np.full(shape, 0.01)):
        ref = _reference_gray(y, p, v, block, step)
        # Both in float64; the DCTs differ only in summation order (round-off ~1e-15 per coefficient).
        np.testing.assert_allclose(dct_wiener_gray(y, p, v, cfg), ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(dct_wiener_gray(y, p, 0.01, cfg), _reference_gray(y, p, np.full(shape, 0.01), block,
                                                                                 step), rtol=0, atol=1e-10)


def test_with_all_gains_one_the_blocks_put_the_photo_back_together():
    # A pilot 1000x the photo and no noise (variance floored at 1e-12): every gain is 1 to ~1e-12 / (1e6 Y^2),
    # so the weighted overlap-add of the blocks must give the photo back (float32 output), for every block
    # size and step, the edge blocks included.
    rng = np.random.default_rng(1)
    y = rng.random((20, 26, 3))
    for cfg in (WienerConfig(), WienerConfig(block_px=8, step_px=3), WienerConfig(block_px=4, step_px=1)):
        np.testing.assert_allclose(dct_wiener(y, 1e3 * y, 0.0, cfg), y, atol=1e-5)
    # and a noise std far below the pilot's coefficients changes the photo by about that much at most
    pilot = np.clip(y + rng.normal(0, 0.2, y.shape), 0.05, 1)
    assert np.abs(dct_wiener(y, pilot, 1e-4) - y).max() < 1e-2


def _textured(h: int, w: int) -> np.ndarray:
    """Fine texture (periods of 4-25 px) and edges, three correlated channels."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = 0.5 + 0.2 * np.sin(xx * 1.1) * np.cos(yy * 0.7) + 0.15 * np.sign(np.sin(xx * 0.4 + yy * 0.25))
    return np.clip(np.stack([base, 0.8 * base + 0.1, 1.0 - 0.7 * base], axis=-1), 0, 1).astype(np.float32)


def test_an_exact_pilot_gives_the_oracle_wiener_gain():
    # With the clean photo as the pilot the step is the oracle Wiener filter of each block: far below the noise.
    rng = np.random.default_rng(2)
    clean = _textured(64, 80)
    sigma = 0.1
    noisy = clean + rng.normal(0, sigma, clean.shape)
    out = dct_wiener(noisy, clean, sigma)
    mse_noisy = np.mean((noisy - clean) ** 2)
    mse_out = np.mean((out - clean) ** 2)
    assert mse_out < 0.25 * mse_noisy, (mse_out, mse_noisy)


def test_a_blurred_pilot_gets_its_detail_back_from_the_noisy_photo():
    # The case the step exists for: a pilot that lost detail (a Gaussian blur of 1 px of the clean photo) is
    # refined towards the clean photo, well below both its own error and the noisy photo's (measured over
    # seeds 0-2: 0.57x the pilot's, 0.39x the noisy photo's).
    import cv2

    rng = np.random.default_rng(3)
    clean = _textured(64, 80)
    sigma = 0.08
    noisy = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
    pilot = cv2.GaussianBlur(clean, (0, 0), 1.0)
    out = dct_wiener(noisy, pilot, sigma)
    mse = {k: float(np.mean((x - clean) ** 2)) for k, x in (("noisy", noisy), ("pilot", pilot), ("out", out))}
    assert mse["out"] < 0.75 * mse["pilot"] and mse["out"] < 0.5 * mse["noisy"], mse


def test_a_noise_map_is_used_per_block_and_a_constant_one_is_one_number():
    np.testing.assert_allclose(OPPONENT @ OPPONENT.T, np.eye(3), atol=1e-12)
    import cv2

    rng = np.random.default_rng(4)
    clean = _textured(64, 80)
    pilot = cv2.GaussianBlur(clean, (0, 0), 1.0)
    noisy = clean + rng.normal(0, 0.05, clean.shape)
    np.testing.assert_allclose(dct_wiener(noisy, pilot, 0.05), dct_wiener(noisy, pilot, np.full(clean.shape, 0.05)),
                               atol=1e-6)
    # Noise of 0.02 on the left half and 0.15 on the right: the map beats its RMS as one number (0.87x the
    # error over seeds 0-2), since each block is shrunk by its own noise.
    smap = np.where(np.arange(80)[None, :, None] < 40, 0.02, 0.15) * np.ones(clean.shape)
    noisy = clean + rng.normal(0, 1, clean.shape) * smap
    per_pixel = np.mean((dct_wiener(noisy, pilot, smap) - clean) ** 2)
    one = np.mean((dct_wiener(noisy, pilot, float(np.sqrt(np.mean(smap ** 2)))) - clean) ** 2)
    assert per_pixel < 0.95 * one, (per_pixel, one)


def test_gray_photos_small_photos_and_bad_input():
    rng = np.random.default_rng(5)
    g = rng.random((10, 12))
    assert dct_wiener(g, g, 0.1).shape == (10, 12)
    tiny = rng.random((5, 6, 3))
    pilot = rng.random((5, 6, 3))
    np.testing.assert_allclose(dct_wiener(tiny, pilot, 0.1), pilot, atol=1e-6)  # smaller than a block: the pilot
    with pytest.raises(ValueError, match="shape"):
        dct_wiener(g, g[:, :5], 0.1)
    with pytest.raises(ValueError, match="WienerConfig"):
        WienerConfig(block_px=8, step_px=9)


@pytest.mark.parametrize("method", ["r2r", "neighbor2neighbor", "n2v"])
def test_denoise_with_method_refines_the_network_output_before_the_clipping_correction(method):
    # The network's output (same seed, so the same passes) is the pilot; the noisy photo is filtered at the
    # noise std the method uses; the clipping correction (R2R, Neighbor2Neighbor) comes after.
    import torch

    from denoise.clipping import clipped_sides, undo_clipping_bias
    from denoise.n2v import N2VConfig
    from denoise.self_supervised import denoise_with_method, r2r_noise_std, train_with_method
    from denoise.unet import UNetConfig

    rng = np.random.default_rng(6)
    clean = _textured(40, 40)
    clean[:, :12] = 0.0  # a black band: the clipping correction applies
    noisy = [np.clip(clean + 0.1 * rng.standard_normal(clean.shape), 0, 1).astype(np.float32) for _ in range(2)]
    cfg = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=3, batch_size=2, patch_px=16, method=method)
    model = train_with_method(noisy, cfg, seed=0)
    wcfg = WienerConfig(block_px=8, step_px=2)
    raw = denoise_with_method(model, noisy, cfg, passes=2, seed=1, undo_clipping=False, noise_sigma=0.1)
    got = denoise_with_method(model, noisy, cfg, passes=2, seed=1, wiener=wcfg, noise_sigma=0.1)
    for img, r, g in zip(noisy, raw, got, strict=True):
        ref = np.clip(dct_wiener(img, r, 0.1, wcfg), 0, 1)
        if method != "n2v":
            low, high = clipped_sides(img)
            ref = undo_clipping_bias(torch.from_numpy(ref).permute(2, 0, 1), torch.tensor(0.1), low=low,
                                     high=high).permute(1, 2, 0).numpy()
        np.testing.assert_allclose(g, ref, atol=1e-6)
        assert np.abs(g - r).max() > 1e-3  # the step did something
    # The per-pixel noise map R2R may use reaches the step in the image's layout.
    stds = [r2r_noise_std(img, noise_model="curve") for img in noisy]
    assert all(isinstance(s, torch.Tensor) and s.shape == (3, 40, 40) for s in stds)
    if method == "r2r":
        out = denoise_with_method(model, noisy, cfg, passes=1, seed=1, wiener=wcfg, noise_sigma=stds,
                                  undo_clipping=False)
        raw1 = denoise_with_method(model, noisy, cfg, passes=1, seed=1, noise_sigma=stds, undo_clipping=False)
        ref = np.clip(dct_wiener(noisy[0], raw1[0], stds[0].permute(1, 2, 0).numpy(), wcfg), 0, 1)
        np.testing.assert_allclose(out[0], ref, atol=1e-6)


@pytest.mark.parametrize("idx", [[0, 2, 4, 6, 7], [3], [0, 5], [1, 2, 3], [0, 3, 6, 8, 9]])
def test_strided_parts_cover_the_indices_in_order(idx):
    idx = np.asarray(idx)
    got = []
    for src, dst in _strided_parts(idx):
        np.testing.assert_array_equal(np.arange(len(idx))[src], np.arange(src.start, src.stop))
        got += list(np.arange(dst.start, dst.stop, dst.step) if isinstance(dst, slice) else dst)
    assert got == list(idx)


def test_a_gray_photo_read_as_rgb_is_filtered_as_the_gray_photo():
    """Three equal channels hold the same noise, not independent noise: in the opponent space the luminance
    would hold 3x the variance the gains assume (the filter too weak: 27.54 against 27.79 dB on a DTU scan24 crop
    at sigma 25/255). Such a photo is filtered as the gray one, its pilot's channels averaged."""
    rng = np.random.default_rng(8)
    clean = _textured(40, 44)[..., 0].astype(np.float64)
    noisy = clean + rng.normal(0, 0.1, clean.shape)
    pilot = clean + rng.normal(0, 0.02, clean.shape)
    rgb, prgb = (np.repeat(a[..., None], 3, axis=2) for a in (noisy, pilot))
    prgb = prgb + np.array([0.0, 0.01, -0.01])  # a pilot with a little colour: its channels' mean is the gray one
    want = np.repeat(dct_wiener(noisy, pilot, 0.1)[..., None], 3, axis=2)
    np.testing.assert_allclose(dct_wiener(rgb, prgb, 0.1), want, atol=1e-6)
    np.testing.assert_allclose(dct_wiener(rgb, prgb, np.full(rgb.shape, 0.1)), want, atol=1e-6)

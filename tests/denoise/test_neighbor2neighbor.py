"""Neighbor2Neighbor and Recorrupted-to-Recorrupted on the N2V UNet: sub-sampler, losses, training, CLI."""

import json

import numpy as np
import pytest
import torch

from denoise.cli import main
from denoise.losses import neighbor2neighbor_loss
from denoise.n2v import N2VConfig, train_n2v
from denoise.neighbor2neighbor import NEIGHBOUR_PAIRS, neighbour_choice, neighbour_subsample
from denoise.r2r import recorrupt
from denoise.self_supervised import denoise_with_method, r2r_noise_std, train_self_supervised, train_with_method
from denoise.unet import UNetConfig
from mvgeo.common.errors import ConfigError, InputError, ShapeError
from mvgeo.common.imageio import write_image
from tests.denoise._synth import add_noise, psnr, smooth_scene


def _subsample_loop(x: np.ndarray, choice: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slow reference: for every 2x2 cell, copy the two chosen pixels one by one."""
    b, c, h, w = x.shape
    g1 = np.zeros((b, c, h // 2, w // 2))
    g2 = np.zeros_like(g1)
    for n in range(b):
        for i in range(h // 2):
            for j in range(w // 2):
                first, second = NEIGHBOUR_PAIRS[choice[n, i, j]]
                y1, x1 = 2 * i + first // 2, 2 * j + first % 2
                y2, x2 = 2 * i + second // 2, 2 * j + second % 2
                g1[n, :, i, j] = x[n, :, y1, x1]
                g2[n, :, i, j] = x[n, :, y2, x2]
    return g1, g2


def test_neighbour_pairs_are_the_eight_ordered_edge_neighbours():
    assert len(set(NEIGHBOUR_PAIRS)) == 8
    for a, b in NEIGHBOUR_PAIRS:
        (ya, xa), (yb, xb) = divmod(a, 2), divmod(b, 2)
        assert abs(ya - yb) + abs(xa - xb) == 1  # share an edge: never the same pixel, never diagonal


@pytest.mark.parametrize("h, w", [(8, 10), (7, 9)])  # odd sizes drop the last row / column
def test_neighbour_subsample_matches_loop(rng, h, w):
    x = torch.from_numpy(rng.random((2, 3, h, w)))
    gen = torch.Generator().manual_seed(3)
    choice = neighbour_choice(2, h, w, generator=gen)
    assert choice.shape == (2, h // 2, w // 2) and int(choice.min()) >= 0 and int(choice.max()) <= 7
    g1, g2 = neighbour_subsample(x, choice)
    r1, r2 = _subsample_loop(x.numpy(), choice.numpy())
    np.testing.assert_array_equal(g1.numpy(), r1)
    np.testing.assert_array_equal(g2.numpy(), r2)
    with pytest.raises(ShapeError):
        neighbour_subsample(x, choice[:, :-1])
    with pytest.raises(ShapeError):
        neighbour_choice(1, 1, 4)


def test_neighbour_choice_covers_all_pairs():
    choice = neighbour_choice(4, 32, 32, generator=torch.Generator().manual_seed(0))
    counts = torch.bincount(choice.flatten(), minlength=8).double()
    # 1024 cells, 8 equally likely pairs: 128 each, binomial std ~10.6; 5 std either way.
    assert counts.min() > 128 - 53 and counts.max() < 128 + 53


def test_nb2nb_loss_reference_zero_and_stop_gradient(rng):
    t = [torch.from_numpy(rng.random((2, 3, 5, 6))) for _ in range(4)]
    pred = t[0].clone().requires_grad_(True)
    full1 = t[2].clone().requires_grad_(True)
    loss = neighbor2neighbor_loss(pred, t[1], full1, t[3], gamma=1.5)
    d = t[0] - t[1]
    ref = (d**2 + 1.5 * (d - (t[2] - t[3])) ** 2).mean()
    assert loss.item() == pytest.approx(ref.item(), rel=1e-12)
    loss.backward()
    assert full1.grad is None  # f(y) is a stop-gradient term
    assert neighbor2neighbor_loss(t[0], t[0], t[2], t[2], gamma=2.0).item() == 0.0
    assert neighbor2neighbor_loss(t[0], t[1], t[2], t[3], reduction="none").shape == (2,)
    with pytest.raises(ValueError, match="gamma"):
        neighbor2neighbor_loss(t[0], t[1], t[2], t[3], gamma=-1.0)


def test_recorrupt_gives_independent_noise_of_the_right_size():
    # y = 0 + n: the input's and target's noise (n + a z, n - z / a) are uncorrelated, with
    # variances s^2 (1 + a^2) and s^2 (1 + 1 / a^2).
    gen = torch.Generator().manual_seed(0)
    s, a = 0.1, 0.5
    n = s * torch.randn((4, 3, 128, 128), generator=gen, dtype=torch.float64)
    inp, tgt = recorrupt(n, s, alpha=a, generator=gen)
    m = n.numel()
    # Sample statistics of ~200k values: relative std of a variance ~ sqrt(2 / m) = 0.3 %.
    assert inp.var().item() == pytest.approx(s * s * (1 + a * a), rel=0.02)
    assert tgt.var().item() == pytest.approx(s * s * (1 + 1 / (a * a)), rel=0.02)
    corr = torch.corrcoef(torch.stack([inp.flatten(), tgt.flatten()]))[0, 1].item()
    assert abs(corr) < 5 / np.sqrt(m)  # 5 standard errors of a zero correlation
    # Per-channel sigma broadcasts.
    inp, _ = recorrupt(torch.zeros(1, 3, 64, 64), torch.tensor([0.0, 0.1, 0.0]).reshape(1, 3, 1, 1), alpha=a,
                       generator=gen)
    assert inp[:, 0].abs().max().item() == 0.0 and inp[:, 1].std().item() > 0.03
    with pytest.raises(ValueError, match="alpha"):
        recorrupt(n, s, alpha=0.0)


def test_config_method_validation():
    with pytest.raises(ConfigError, match="method"):
        N2VConfig(method="noise2noise")
    with pytest.raises(ConfigError, match="r2r_alpha"):
        N2VConfig(r2r_alpha=0.0)
    with pytest.raises(ConfigError, match="nb2nb_gamma"):
        N2VConfig(nb2nb_gamma=-1.0)
    with pytest.raises(ValueError, match="n2v"):
        train_self_supervised([np.zeros((8, 8, 3), np.float32)], N2VConfig())
    with pytest.raises(ConfigError, match="train_with_method"):  # train_n2v never trains another method
        train_n2v([np.zeros((8, 8, 3), np.float32)], N2VConfig(method="r2r"))


@pytest.mark.parametrize("method", ["neighbor2neighbor", "r2r"])
def test_training_denoises(rng, method):
    # Two 64x64 piecewise-smooth images at sigma 25/255, a width-8 depth-2 UNet, 250 steps of
    # 4 patches of 24 px (3-6 s on the shared machine under load).
    clean = [smooth_scene(rng, 64, 64) for _ in range(2)]
    noisy = [add_noise(rng, c, 25 / 255) for c in clean]
    cfg = N2VConfig(unet=UNetConfig(width=8, depth=2), steps=250, batch_size=4, patch_px=24, method=method)
    model = train_with_method(noisy, cfg, seed=0)
    assert not model.blind_spot and len(model.history) == cfg.steps
    out = denoise_with_method(model, noisy, cfg, passes=2, seed=0)
    gain = np.mean([psnr(o, c) - psnr(n, c) for o, n, c in zip(out, noisy, clean, strict=True)])
    # Measured with this fixture's images: +9.3 dB (neighbor2neighbor) and +9.2 dB (r2r); with
    # 32 px patches after 150 steps +4.5 / +9.1 dB, after 1 step (the untrained start, a smoother
    # that ignores the centre pixel) -1.4 dB; an identity network gives 0 dB. 5 dB fails a method
    # that does not learn and leaves room for BLAS / thread-count differences.
    assert gain > 5.0, gain


@pytest.mark.parametrize("method", ["neighbor2neighbor", "r2r"])
def test_training_is_seeded(rng, method):
    noisy = [add_noise(rng, smooth_scene(rng, 24, 24), 0.1) for _ in range(2)]
    cfg = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=3, batch_size=2, patch_px=16, method=method)
    a, b, c = (train_with_method(noisy, cfg, seed=s) for s in (0, 0, 1))
    assert a.history == b.history and a.history != c.history


def test_r2r_noise_levels_and_n2v_route(rng):
    noisy = [add_noise(rng, smooth_scene(rng, 24, 24), 0.1) for _ in range(2)]
    cfg = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=2, batch_size=2, patch_px=16, method="r2r")
    with pytest.raises(InputError, match="3 noise levels for 2 images"):
        train_self_supervised(noisy, cfg, noise_sigma=[0.1, 0.1, 0.1])
    model = train_self_supervised(noisy, cfg, noise_sigma=0.1)
    out = denoise_with_method(model, noisy, cfg, passes=0, noise_sigma=[0.1, 0.1])  # passes 0: one draw
    assert out[0].shape == (24, 24, 3) and out[0].dtype == np.float32
    n2v = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=2, batch_size=2, patch_px=16)
    m = train_with_method(noisy, n2v, seed=0)
    assert m.blind_spot
    assert len(denoise_with_method(m, noisy, n2v, passes=1)) == 2


@pytest.mark.parametrize("method", ["neighbor2neighbor", "r2r"])
def test_given_noise_estimates_are_the_estimated_ones(rng, method):
    """The pipeline's denoise stage estimates each photo's std once (`r2r_noise_std`) and passes it in:
    training and inference then match estimating inside, bit for bit, for a number and for a per-pixel map
    (shot noise, the second image)."""
    noisy = [add_noise(rng, smooth_scene(rng, 32, 32), 0.1), _poisson_gaussian(rng, smooth_scene(rng, 96, 96), 0.01,
                                                                               2 / 255)]
    stds = [r2r_noise_std(im) for im in noisy]
    assert isinstance(stds[0], float) and isinstance(stds[1], torch.Tensor)
    cfg = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=3, batch_size=2, patch_px=16, method=method)
    inside = train_with_method(noisy, cfg, seed=0)
    given = train_with_method(noisy, cfg, seed=0, noise_sigma=stds)
    assert inside.history == given.history
    a = denoise_with_method(inside, noisy, cfg, passes=2, seed=1)
    b = denoise_with_method(given, noisy, cfg, passes=2, seed=1, noise_sigma=stds)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    c = denoise_with_method(given, noisy, cfg, passes=2, seed=1, noise_sigma=[2 * s for s in stds])
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))  # the given ones are the ones used


def test_cli_method_flag(tmp_path, rng):
    src = tmp_path / "noisy"
    src.mkdir()
    for k in range(2):
        write_image(src / f"{k}.png", add_noise(rng, smooth_scene(rng, 40, 40), 0.1))
    out = tmp_path / "out"
    assert main(["n2v", str(src), "--out", str(out), "--steps", "3", "--passes", "1", "--preset", "fast",
                 "--method", "neighbor2neighbor"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["method"] == "neighbor2neighbor" and len(list((out / "images").iterdir())) == 2
    with pytest.raises(SystemExit):
        main(["n2v", str(src), "--out", str(tmp_path / "o2"), "--method", "bogus"])


def _poisson_gaussian(rng, img, gain, floor_std):
    return np.clip(gain * rng.poisson(img / gain) + floor_std * rng.standard_normal(img.shape), 0, 1).astype(np.float32)


def test_r2r_noise_std_follows_the_noise_model(rng):
    # Gaussian noise: "auto" gives one number near the true std; shot noise (gain 0.01, floor 2/255):
    # a per-pixel map near the true std sqrt(gain * x + floor^2) at the clean intensity. 15% on the
    # median relative error: the curve is fitted from 8 intensity bins of one 96x96 image and
    # evaluated at a 2-px blur of the noisy image (edges move the blur off the clean value).
    clean = smooth_scene(rng, 96, 96)
    sigma = r2r_noise_std(add_noise(rng, clean, 0.1))
    assert isinstance(sigma, float) and abs(sigma - 0.1) < 0.01
    gain, floor_std = 0.01, 2 / 255
    noisy = _poisson_gaussian(rng, clean, gain, floor_std)
    sig_map = r2r_noise_std(noisy)
    assert isinstance(sig_map, torch.Tensor) and sig_map.shape == (3, 96, 96)
    truth = np.sqrt(gain * clean + floor_std**2).transpose(2, 0, 1)
    assert np.median(np.abs(sig_map.numpy() / truth - 1)) < 0.15
    assert isinstance(r2r_noise_std(noisy, noise_model="constant"), float)
    assert isinstance(r2r_noise_std(add_noise(rng, clean, 0.1), noise_model="curve"), torch.Tensor)
    with pytest.raises(ValueError, match="noise_model"):
        r2r_noise_std(noisy, noise_model="poisson")


@pytest.mark.parametrize("noise_model", ["constant", "curve"])
def test_r2r_inference_matches_dihedral_reference(rng, noise_model):
    # denoise_with_method's R2R inference against the obvious loop: pass k recorrupts with the k-th
    # draw of the seeded generator (scaled by the image's std, or by its per-pixel map from the
    # noise curve at the 2-px blur), runs the network on the (k % 8)-th rotation / reflection,
    # undoes it; the output is the mean. 10 passes cover all 8 transforms and wrap around.
    import cv2

    from denoise.inference import dihedral
    from denoise.noise_level import estimate_noise_curve, estimate_noise_sigma_pca

    noisy = [_poisson_gaussian(rng, smooth_scene(rng, 20, 28), 0.01, 0.02) for _ in range(2)]
    cfg = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=3, batch_size=2, patch_px=16, method="r2r")
    model = train_self_supervised(noisy, cfg, seed=0, noise_model=noise_model)
    got = denoise_with_method(model, noisy, cfg, passes=10, seed=3, noise_model=noise_model)
    gen = torch.Generator().manual_seed(3)
    for img, out in zip(noisy, got, strict=True):
        if noise_model == "constant":
            sigma = estimate_noise_sigma_pca(img, exclude_clipped=True)
        else:
            curve = estimate_noise_curve(img)
            mu = np.clip(cv2.GaussianBlur(img, (0, 0), 2.0), 0, 1)
            sigma = torch.from_numpy(np.sqrt(np.maximum(curve.gain * mu + curve.floor, 0))).permute(2, 0, 1)
        x = torch.from_numpy(img).permute(2, 0, 1)[None].float()
        acc = torch.zeros_like(x)
        with torch.no_grad():
            for k in range(10):
                z = torch.randn(x.shape, generator=gen)
                acc += dihedral(model.apply(dihedral(x + cfg.r2r_alpha * sigma * z, k)), k, inverse=True)
        ref = (acc[0] / 10).clamp(0, 1).permute(1, 2, 0).numpy()
        np.testing.assert_allclose(out, ref, atol=1e-5)  # float32 sums in another order

"""N2V training: schedule, loss, determinism, and that it really denoises."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from denoise.inference import denoise_images
from denoise.n2v import N2VConfig, lr_factor, masked_mse, n2v_preset, new_model, train_n2v
from denoise.unet import UNetConfig
from mvgeo.common.errors import ConfigError, InputError
from tests.denoise._synth import add_noise, psnr, smooth_scene

TINY = N2VConfig(unet=UNetConfig(width=4, depth=2), steps=3, batch_size=2, patch_px=16)


def test_lr_schedule():
    kw = dict(steps=100, warmup_frac=0.1, min_lr_frac=0.01)
    assert lr_factor(0, **kw) == pytest.approx(0.1)
    assert lr_factor(9, **kw) == pytest.approx(1.0)
    assert lr_factor(10, **kw) == pytest.approx(1.0)
    # Halfway through the cosine part: min + (1 - min) / 2.
    assert lr_factor(55, **kw) == pytest.approx(0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert lr_factor(100, **kw) == pytest.approx(0.01)


def test_masked_mse_reference(rng):
    out = torch.from_numpy(rng.random((2, 3, 4, 5)))
    tgt = torch.from_numpy(rng.random((2, 3, 4, 5)))
    mask = torch.from_numpy(rng.random((2, 1, 4, 5)) < 0.3)
    m = mask.expand(-1, 3, -1, -1)
    ref = ((out - tgt)[m] ** 2).mean()
    assert masked_mse(out, tgt, mask).item() == pytest.approx(ref.item(), rel=1e-12)
    assert masked_mse(out, tgt, torch.zeros_like(mask)).item() == 0.0


def test_config_validation_and_presets():
    with pytest.raises(ConfigError, match="mask_prob"):
        N2VConfig(mask_prob=0.0)
    with pytest.raises(ConfigError, match="replacement"):
        N2VConfig(replacement="zeros")
    with pytest.raises(ConfigError, match="preset"):
        n2v_preset("huge")
    assert n2v_preset("fast", steps=5).steps == 5
    assert n2v_preset("n2v2").unet.blurpool and not n2v_preset("n2v2").unet.top_skip


def test_training_is_seeded_and_leaves_global_rng(rng):
    imgs = [add_noise(rng, smooth_scene(rng, 24, 24), 0.1) for _ in range(2)]
    state = torch.random.get_rng_state()
    a = train_n2v(imgs, TINY, seed=3)
    b = train_n2v(imgs, TINY, seed=3)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert a.history == b.history
    for pa, pb in zip(a.unet.parameters(), b.unet.parameters(), strict=True):
        assert torch.equal(pa, pb)
    c = train_n2v(imgs, TINY, seed=4)
    assert c.history != a.history


def test_bad_inputs():
    with pytest.raises(InputError):
        train_n2v([], TINY)
    bad = np.zeros((8, 8, 3), np.float32)
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="image 0"):
        train_n2v([bad], TINY)
    with pytest.raises(InputError, match="dtype"):
        train_n2v([np.zeros((8, 8, 3), np.uint8)], TINY)
    with pytest.raises(InputError, match="1x8"):
        train_n2v([np.zeros((8, 1, 3), np.float32)], TINY)


def test_n2v_denoises_smooth_scenes(rng):
    # The real check of the method: self-supervised training on the noisy images only must
    # beat the noisy input by a wide margin on piecewise-smooth scenes at sigma = 25/255.
    clean = [smooth_scene(rng, 64, 64) for _ in range(3)]
    noisy = [add_noise(rng, c, 25 / 255) for c in clean]
    # The fast preset's network at a test-sized schedule (the preset's 400 x 8 patches of 64 px
    # take minutes on the shared machine).
    cfg = n2v_preset("fast", steps=200, batch_size=4, patch_px=48)
    model = train_n2v(noisy, cfg, seed=0)
    assert np.mean(model.history[-10:]) < np.mean(model.history[:10])
    out = denoise_images(model, noisy, passes=2, seed=0, fuse=False)
    gain = np.mean([psnr(o, c) - psnr(n, c) for o, n, c in zip(out, noisy, clean, strict=True)])
    # The network alone (fuse=False; the centre-pixel fusion is tested in test_fusion.py).
    # Measured +4.0 dB with this seed (lr 1e-3, 200 steps); 3 dB leaves margin for BLAS /
    # thread-count differences while failing for an identity or a broken (self-copying) training.
    assert gain > 3.0, gain


def test_training_threads_fix_the_network(rng):
    """The trained weights do not depend on the caller's torch thread count (a Ray task's 1 CPU, a
    workstation's cores): each of `batch_chunks` chunks runs on one torch thread (`denoise.parallel`), and the
    caller's count is restored. The control shows the count would matter at this size: the same batch
    through the network on 1 and on 3 intra-op threads gives different weight gradients (oneDNN sums
    them in per-thread chunks)."""
    imgs = [add_noise(rng, smooth_scene(rng, 64, 64), 0.1) for _ in range(2)]
    cfg = N2VConfig(unet=UNetConfig(width=16, depth=2), steps=4, batch_size=8, patch_px=64)
    saved = torch.get_num_threads()

    def weights(outer: int, config: N2VConfig) -> torch.Tensor:
        torch.set_num_threads(outer)
        try:
            m = train_n2v(imgs, config, seed=0)
            assert torch.get_num_threads() == outer
        finally:
            torch.set_num_threads(saved)
        return torch.cat([p.detach().flatten() for p in m.unet.parameters()])

    assert torch.equal(weights(1, cfg), weights(3, cfg))
    one = dataclasses.replace(cfg, batch_chunks=1)
    assert torch.equal(weights(1, one), weights(3, one))

    net = new_model(cfg, [torch.from_numpy(i.transpose(2, 0, 1).copy()) for i in imgs], seed=0).unet
    x = torch.randn(8, 3, 64, 64, generator=torch.Generator().manual_seed(1))

    def gradient(threads: int) -> torch.Tensor:
        torch.set_num_threads(threads)
        try:
            net.zero_grad()
            net(x).square().mean().backward()
        finally:
            torch.set_num_threads(saved)
        return torch.cat([p.grad.flatten() for p in net.parameters()])

    assert not torch.equal(gradient(1), gradient(3))
    with pytest.raises(ConfigError, match="batch_chunks"):
        N2VConfig(batch_chunks=0)

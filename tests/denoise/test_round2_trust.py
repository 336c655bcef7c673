"""Round 2's safeguards: the trust target, the J-invariant prediction, the guard, the Charbonnier ablation."""

import numpy as np
import pytest
import torch

from denoise.n2v import N2VConfig, train_n2v
from denoise.round2 import (
    Round2Config,
    blind_spot_blocks,
    blind_spot_loss,
    guard_decision,
    jinvariant_predict,
    joint_loss,
    refine_round2,
    render_trust_target,
    spread_cells,
)
from denoise.unet import UNetConfig
from mvgeo.common.errors import ConfigError
from tests.denoise._synth import add_noise, psnr, smooth_scene


def _t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].double()


def _tiny_model(rng, noisy):
    return train_n2v(noisy, N2VConfig(unet=UNetConfig(width=4), steps=20, batch_size=2, patch_px=32, lr=2e-3),
                     seed=0)


def test_trust_target_follows_the_better_estimate(rng):
    sigma = 25 / 255
    clean = smooth_scene(rng, 64, 64)
    noisy = add_noise(rng, clean, sigma)
    y, x = _t(noisy), _t(clean)
    # A mediocre round-1 prediction: the clean image plus a smooth error of 0.1 (larger than the
    # floor of the local statistics, so the estimates can see it).
    mu = x + 0.1 * torch.sin(torch.arange(64, dtype=x.dtype) / 4.0)[None, None, None, :]
    good = render_trust_target(y, mu, x, noise_sigma=sigma)
    # A correct render is trusted where round 1 is off, and the target beats round 1.
    assert float(good.render_weight.mean()) > 0.6
    assert 0.0 <= float(good.render_weight.min()) and float(good.render_weight.max()) <= 1.0
    err = lambda a: float(((a - x) ** 2).mean())  # noqa: E731
    assert err(good.target) < 0.7 * err(good.round1)
    # A render that is wrong by far more than the noise (a 0.3 offset) is ignored: the target
    # stays within a few percent of round 1's error.
    bad = render_trust_target(y, mu, x + 0.3, noise_sigma=sigma)
    assert float(bad.render_weight.mean()) < 0.15
    assert err(bad.target) < 1.1 * err(bad.round1)


def test_trust_target_two_perfect_estimates_average():
    # Noise-free photo, round 1 and render all equal the truth: both error estimates are at the
    # floor, so the weight is exactly 1/2 and the target is the truth.
    x = torch.full((1, 3, 16, 16), 0.5, dtype=torch.float64)
    tt = render_trust_target(x, x, x, noise_sigma=0.05)
    assert torch.allclose(tt.render_weight, torch.full_like(x, 0.5))
    assert torch.allclose(tt.target, x)


def test_jinvariant_prediction_ignores_each_pixel_own_value(rng):
    noisy = [add_noise(rng, smooth_scene(rng, 32, 32), 0.1)]
    model = _tiny_model(rng, noisy)
    y = _t(noisy[0]).float()
    base = jinvariant_predict(model, y, generator=torch.Generator().manual_seed(3))
    for (i, j) in [(0, 0), (7, 12)]:
        z = y.clone()
        z[..., i, j] += 0.7  # the network never sees this value when predicting (i, j)
        out = jinvariant_predict(model, z, generator=torch.Generator().manual_seed(3))
        # Exact: the changed value is absent from the input of the pass that predicts (i, j).
        assert torch.equal(out[..., i, j], base[..., i, j])
        # Control: the neighbours' predictions do see it (the test could fail).
        assert not torch.equal(out, base)


def test_blind_spot_loss_estimates_noise_plus_error(rng):
    # J-invariance makes the noise and the prediction error uncorrelated: E (y - f_J)^2 = sigma^2 + MSE.
    sigma = 0.1
    clean = smooth_scene(rng, 48, 48)
    noisy = [add_noise(rng, clean, sigma)]
    model = _tiny_model(rng, noisy)
    y = torch.from_numpy(noisy[0].transpose(2, 0, 1).copy())
    pred = jinvariant_predict(model, y[None], generator=torch.Generator().manual_seed(1))
    mse = float(((pred[0] - torch.from_numpy(clean.transpose(2, 0, 1).copy())) ** 2).mean())
    est = blind_spot_loss(model, [y], seed=1)
    # 48*48*3 = 6912 samples: the noise term's sampling std is sigma^2 sqrt(2/6912) ~ 1.7% of sigma^2,
    # plus clipping of the noisy image at 0/1 (few pixels in [0.1, 0.9]); 10% of sigma^2 is ~6 std.
    assert est == pytest.approx(sigma**2 + mse, abs=0.1 * sigma**2)


def test_jinvariant_cells_equal_the_full_prediction_there(rng):
    noisy = [add_noise(rng, smooth_scene(rng, 30, 35), 0.1)]
    model = _tiny_model(rng, noisy)
    y = _t(noisy[0]).float()
    full = jinvariant_predict(model, y, generator=torch.Generator().manual_seed(5))
    cells = [(0, 0), (3, 1), (4, 4)]
    part = jinvariant_predict(model, y, cells=cells, generator=torch.Generator().manual_seed(5))
    rows = torch.arange(30)[:, None] % 5
    cols = torch.arange(35)[None, :] % 5
    run = torch.zeros(30, 35, dtype=torch.bool)
    for a, b in cells:
        run |= (rows == a) & (cols == b)
    # Bit for bit on the selected cells (each skipped pass still draws its replacements), NaN elsewhere.
    assert torch.equal(part[..., run], full[..., run])
    assert torch.isnan(part[..., ~run]).all() and not torch.isnan(full).any()


def test_spread_cells_cover_every_grid_row_and_column():
    five = spread_cells(5)
    assert sorted(a for a, _ in five) == list(range(5)) and sorted(b for _, b in five) == list(range(5))
    every = spread_cells(25)
    assert len(set(every)) == 25
    with pytest.raises(ValueError):
        spread_cells(26)
    with pytest.raises(ConfigError, match="guard_cells"):
        Round2Config(guard_cells=0)


def test_blind_spot_loss_on_a_fifth_of_the_cells_tracks_the_full_one(rng):
    # The guard scores 5 of the 25 cells. On the same seed the subset mean is a sample of the full
    # mean's per-pixel terms: 48*48*3/5 = 1382 values; their relative sampling std for the noise
    # term is sqrt(2/1382) ~ 3.8%, so 15% is ~4 std.
    sigma = 0.1
    noisy = [add_noise(rng, smooth_scene(rng, 48, 48), sigma) for _ in range(2)]
    model = _tiny_model(rng, noisy)
    ys = [torch.from_numpy(n.transpose(2, 0, 1).copy()) for n in noisy]
    full = blind_spot_loss(model, ys, seed=2)
    part = blind_spot_loss(model, ys, seed=2, cells=spread_cells(5))
    assert part == pytest.approx(full, rel=0.15)


def test_blind_spot_loss_keeps_a_nan_the_network_produces(rng):
    # The skipped cells are excluded by position, not by dropping NaNs: a network that returns NaN
    # at a scored pixel must score NaN (which the guard treats as worse), not a lower loss.
    import dataclasses

    noisy = [add_noise(rng, smooth_scene(rng, 20, 20), 0.1)]
    model = _tiny_model(rng, noisy)

    class HoleyModel(type(model)):
        def apply(self, x):
            out = super().apply(x).clone()
            out[..., 0, 0] = float("nan")
            return out

    holey = HoleyModel(**{f.name: getattr(model, f.name) for f in dataclasses.fields(model)})
    ys = [torch.from_numpy(n.transpose(2, 0, 1).copy()) for n in noisy]
    assert (0, 0) in spread_cells(5)
    assert np.isnan(blind_spot_loss(holey, ys, seed=0, cells=spread_cells(5)))
    assert np.isfinite(blind_spot_loss(model, ys, seed=0, cells=spread_cells(5)))


def test_refine_guard_reverts_when_targets_are_wrong(rng):
    clean = [smooth_scene(rng, 48, 48) for _ in range(2)]
    noisy = [add_noise(rng, c, 25 / 255) for c in clean]
    model = _tiny_model(rng, noisy)
    # Renders that are plainly wrong (inverted images): without trust and guard, fine-tuning
    # towards them raises the blind-spot loss, and the guard must keep round 1.
    wrong = [1.0 - c for c in clean]
    cfg = Round2Config(steps=30, batch_size=4, patch_px=32, lr=1e-3, trust_render=False)
    out, rep = refine_round2(model, noisy, wrong, cfg, seed=0)
    assert rep.reverted and out is model and rep.loss_after > rep.loss_before
    # With correct renders the fine-tuned copy is kept (and the round-1 model is untouched).
    before = [p.detach().clone() for p in model.unet.parameters()]
    out2, rep2 = refine_round2(model, noisy, clean, cfg, seed=0)
    assert not rep2.reverted and out2 is not model and not out2.blind_spot
    assert all(torch.equal(a, b) for a, b in zip(before, model.unet.parameters(), strict=True))
    assert rep2.loss_after < rep2.loss_before


def test_charbonnier_ablation_is_a_different_loss(rng):
    x = torch.from_numpy(rng.random((1, 3, 16, 16)))
    r = torch.from_numpy(rng.random((1, 3, 16, 16)))
    joint = joint_loss(x, x, r, Round2Config())
    charb = joint_loss(x, x, r, Round2Config(loss="charbonnier"))
    expected = torch.sqrt((x - r) ** 2 + 1e-6).mean()
    assert charb.total.item() == pytest.approx(expected.item(), rel=1e-9)
    assert joint.total.item() != pytest.approx(charb.total.item(), rel=1e-3)
    with pytest.raises(ConfigError, match="loss"):
        Round2Config(loss="l2")


def test_refine_round2_helps_with_a_good_render(rng):
    # Renders carrying the clean signal: the trust target uses them and round 2 beats round 1.
    from denoise.inference import denoise_images

    clean = [smooth_scene(rng, 48, 48) for _ in range(2)]
    noisy = [add_noise(rng, c, 25 / 255) for c in clean]
    model = _tiny_model(rng, noisy)
    r1 = np.mean([psnr(o, c) for o, c in zip(denoise_images(model, noisy, passes=2), clean, strict=True)])
    out, rep = refine_round2(model, noisy, clean, Round2Config(steps=60, batch_size=4, patch_px=32, lr=1e-3),
                             seed=0)
    r2 = np.mean([psnr(o, c) for o, c in zip(denoise_images(out, noisy, passes=2, fuse=True), clean,
                                             strict=True)])
    assert not rep.reverted and np.mean(rep.render_weight) > 0.5
    assert r2 > r1 + 0.5, (r1, r2)


def test_guard_decision_is_a_paired_test():
    rng = np.random.default_rng(0)
    before = 0.01 + 1e-3 * rng.random((12, 5))
    # The same losses: no gain, never kept; a NaN block keeps round 1.
    assert guard_decision(before, before, 2.0)[0] is False
    nan = before.copy()
    nan[3, 2] = np.nan
    assert guard_decision(before, nan, 0.0)[0] is False
    # Pure noise around no change (std 1e-4 per block): the gain is within 2 standard errors.
    noise = before + 1e-4 * rng.standard_normal(before.shape)
    keep, gain, se = guard_decision(before, noise, 2.0)
    d = (before - noise).ravel()
    assert gain == pytest.approx(d.mean(), rel=1e-12) and se == pytest.approx(d.std(ddof=1) / np.sqrt(60), rel=1e-12)
    assert abs(gain) < 2 * se and keep is False
    # A consistent gain of 1e-4 with the same noise is kept; with z = 0 any positive gain is.
    assert guard_decision(before, noise - 1e-4, 2.0)[0] is True
    assert guard_decision(before, before - 1e-9, 0.0)[0] is True
    # One block: no error estimate, any gain counts.
    assert guard_decision(before[:1, :1], before[:1, :1] - 1e-9, 2.0) == (True, pytest.approx(1e-9), 0.0)
    with pytest.raises(ConfigError, match="guard_z"):
        Round2Config(guard_z=-1.0)


def test_blind_spot_blocks_reference(rng):
    """The block means against a direct computation, and `blind_spot_loss` as the old pooled mean: per view
    the mean over every scored pixel of the union of the cells, then the mean over views."""
    noisy = [add_noise(rng, smooth_scene(rng, 23, 31), 25 / 255) for _ in range(2)]
    model = _tiny_model(rng, noisy)
    ys = [torch.from_numpy(np.ascontiguousarray(n.transpose(2, 0, 1))) for n in noisy]
    cells = spread_cells(5)
    means, counts = blind_spot_blocks(model, ys, seed=3, cells=cells)
    gen = torch.Generator().manual_seed(3)
    pooled = []
    for v, y in enumerate(ys):
        sq = ((jinvariant_predict(model, y[None], cells=cells, generator=gen) - y[None]) ** 2)[0].numpy()
        rows, cols = np.mgrid[:23, :31]
        union = np.zeros((23, 31), bool)
        for c, (a, b) in enumerate(cells):
            m = (rows % 5 == a) & (cols % 5 == b)
            union |= m
            assert means[v, c] == pytest.approx(sq[:, m].mean(), rel=1e-6)
            assert counts[v, c] == 3 * m.sum()
        pooled.append(sq[:, union].mean())
    assert blind_spot_loss(model, ys, seed=3, cells=cells) == pytest.approx(np.mean(pooled), rel=1e-6)


def test_refine_guard_keeps_round1_when_finetuning_changes_nothing(rng):
    """A fine-tuning too small to matter (lr 1e-9): the losses differ by noise only, and round 1 is kept,
    so the pipeline can stop instead of paying a second round for the same images."""
    clean = [smooth_scene(rng, 48, 48) for _ in range(2)]
    noisy = [add_noise(rng, c, 25 / 255) for c in clean]
    model = _tiny_model(rng, noisy)
    out, rep = refine_round2(model, noisy, clean, Round2Config(steps=5, batch_size=2, patch_px=32, lr=1e-9), seed=0)
    assert rep.reverted and out is model
    assert abs(rep.loss_before - rep.loss_after) <= 2 * rep.loss_gain_se

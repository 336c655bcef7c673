"""Effects: statistics against their definitions, random streams, validation, needs."""

from __future__ import annotations

import numpy as np
import pytest

from data_synth.effects import EFFECTS, EffectContext, apply_effects, effect_rng, effects_need, parse_effect
from data_synth.effects.blur import disc_kernel, line_kernel
from mvgeo.common.errors import ConfigError

K = np.array([[100.0, 0, 64.0], [0, 100.0, 48.0], [0, 0, 1]])


def _ctx(name="view_000", depth=None):
    return EffectContext(view_name=name, K=K, depth=depth)


def _fx(*tables):
    return tuple(parse_effect(t, key=f"effects[{i}]", path=None) for i, t in enumerate(tables))


def test_all_issue_effects_are_registered():
    assert {"gaussian", "poisson_gaussian", "bayer_noise", "defocus_blur", "motion_blur", "exposure", "vignetting",
            "jpeg", "quantize"} <= set(EFFECTS)


@pytest.mark.parametrize("table", [{"type": "gaussian", "sigma_8bit": 25.0}, {"type": "gaussian", "sigma": 25 / 255}])
def test_gaussian_std_on_flat_grey(table):
    img = np.full((256, 256, 3), 0.5, np.float32)
    out = apply_effects(img, _fx(table), seed=1, ctx=_ctx())
    # 196,608 samples: the std estimate has relative s.e. 1/sqrt(2N) = 0.16 %, far inside 2 %.
    # Clipping at 0 and 1 is 5.1 sigma away from 0.5: negligible.
    assert np.std(out - img) == pytest.approx(25 / 255, rel=0.02)
    assert abs(np.mean(out - img)) < 4 * (25 / 255) / np.sqrt(img.size)


def test_poisson_gaussian_variance_is_affine_in_signal():
    gain, read = 0.01, 3 / 255
    eff = _fx({"type": "poisson_gaussian", "gain": gain, "read_sigma": read, "clip": False})
    for level in (0.1, 0.3, 0.6, 0.9):
        img = np.full((200, 200, 3), level, np.float32)
        out = apply_effects(img, eff, seed=7, ctx=_ctx())
        # 120,000 samples: the variance estimate has relative s.e. ~0.4 %; 3 % tolerance.
        assert np.var(out) == pytest.approx(gain * level + read**2, rel=0.03)
        assert np.mean(out) == pytest.approx(level, abs=4 * np.sqrt((gain * level + read**2) / img.size))


def _demosaic_reference(mosaic: np.ndarray) -> np.ndarray:
    """Per pixel and colour: the sample if the pixel is that colour's site, else the mean of that colour's
    sites among the 8 neighbours inside the image (RGGB from the top-left)."""
    H, W = mosaic.shape
    colour = [[0, 1], [1, 2]]
    out = np.zeros((H, W, 3))
    for y in range(H):
        for x in range(W):
            for c in range(3):
                if colour[y % 2][x % 2] == c:
                    out[y, x, c] = mosaic[y, x]
                    continue
                vals = [mosaic[y + dy, x + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                        if (dy or dx) and 0 <= y + dy < H and 0 <= x + dx < W
                        and colour[(y + dy) % 2][(x + dx) % 2] == c]
                out[y, x, c] = np.mean(vals)
    return out


@pytest.mark.parametrize("shape", [(6, 8), (7, 9)])
def test_bilinear_demosaic_matches_the_per_pixel_definition(shape, rng):
    from data_synth.effects.noise import bilinear_demosaic

    mosaic = rng.normal(size=shape)
    np.testing.assert_allclose(bilinear_demosaic(mosaic), _demosaic_reference(mosaic), atol=1e-12)


def test_bayer_noise_needs_rgb():
    eff = _fx({"type": "bayer_noise", "gain": 0.01, "read_sigma": 0.02})
    with pytest.raises(ValueError, match=r"\(H, W, 3\) RGB"):
        apply_effects(np.full((8, 8, 1), 0.5, np.float32), eff, seed=0, ctx=_ctx())


def test_bayer_noise_is_correlated_between_neighbours_and_has_the_demosaiced_variance():
    from data_synth.effects.noise import bayer_channel_of

    gain, read, level = 0.01, 5 / 255, 0.5
    img = np.full((130, 130, 3), level, np.float32)
    eff = _fx({"type": "bayer_noise", "gain": gain, "read_sigma": read, "clip": False})
    n = np.stack([apply_effects(img, eff, seed=s, ctx=_ctx()) - img for s in range(12)])[:, 1:-1, 1:-1]
    v = gain * level + read**2  # a site's variance
    chan = bayer_channel_of(130, 130)[1:-1, 1:-1]
    # Per colour: its own sites carry v, a site between two of its sites v / 2, between four v / 4.
    # Red: 1/4 own, 1/2 between two, 1/4 between four -> 0.5625 v; green: 1/2 own, 1/2 between four -> 0.625 v.
    # ~200,000 samples per colour: the variance's s.e. is ~0.3 %; 3 % tolerance.
    assert np.var(n[..., 0]) == pytest.approx(0.5625 * v, rel=0.03)
    assert np.var(n[..., 1]) == pytest.approx(0.625 * v, rel=0.03)
    assert np.var(n[..., 2]) == pytest.approx(0.5625 * v, rel=0.03)
    own = np.broadcast_to(chan == 1, n.shape[:3])
    assert np.var(n[..., 1][own]) == pytest.approx(v, rel=0.03)
    # Horizontal neighbours of green: an own site next to one interpolated from it and three others;
    # Poisson-Gaussian noise has none (|r| < 0.02 at these sample counts).
    g = n[..., 1]
    r = np.corrcoef(g[:, :, :-1].ravel(), g[:, :, 1:].ravel())[0, 1]
    assert r > 0.3
    pg = apply_effects(img, _fx({"type": "poisson_gaussian", "gain": gain, "read_sigma": read, "clip": False}),
                       seed=0, ctx=_ctx()) - img
    assert abs(np.corrcoef(pg[:, :-1, 1].ravel(), pg[:, 1:, 1].ravel())[0, 1]) < 0.02
    assert abs(np.mean(n)) < 4 * np.sqrt(v / n.size)


@pytest.mark.parametrize("table", [
    {"type": "defocus_blur", "radius_px": 3.0},
    {"type": "motion_blur", "length_px": 9.0, "angle_deg": 30.0},
    {"type": "motion_blur", "length_px": 5.0},
])
def test_blur_preserves_mean_and_smooths(table, rng):
    img = rng.uniform(size=(128, 128, 3)).astype(np.float32)
    out = apply_effects(img, _fx(table), seed=0, ctx=_ctx())
    # Kernels sum to 1 and borders are reflected: the mean changes only through border
    # effects (O(kernel radius / image size) of the border pixels' deviation): 1e-3 is ample.
    assert np.mean(out) == pytest.approx(np.mean(img), abs=1e-3)
    assert np.std(out) < 0.7 * np.std(img)  # white noise is strongly smoothed


def test_kernels_are_normalised_and_shaped():
    for r in (0.0, 0.7, 2.0, 5.5):
        k = disc_kernel(r)
        assert k.sum() == pytest.approx(1.0, abs=1e-6)
        assert np.allclose(k, k.T) and np.allclose(k, k[::-1])  # symmetric disc
    k = line_kernel(8.0, 0.0)
    assert k.sum() == pytest.approx(1.0, abs=1e-6)
    rows = np.nonzero(k.sum(axis=1) > 1e-6)[0]
    assert len(rows) == 1  # a horizontal line stays in one row
    # The support along x is the stated length (bilinear splat adds at most one pixel).
    cols = np.nonzero(k.sum(axis=0) > 1e-6)[0]
    assert 8 <= np.ptp(cols) + 1 <= 10


def test_depth_dependent_defocus_needs_depth_and_keeps_focus_plane_sharp(rng):
    eff = _fx({"type": "defocus_blur", "radius_px": 4.0, "focus_depth": 2.0})
    assert effects_need(eff) == {"depth"}
    assert effects_need(_fx({"type": "defocus_blur", "radius_px": 4.0})) == frozenset()
    img = rng.uniform(size=(64, 64, 3)).astype(np.float32)
    depth = np.full((64, 64), 2.0, np.float32)
    depth[:, 32:] = np.inf  # background: radius_px at infinity
    out = apply_effects(img, eff, seed=0, ctx=_ctx(depth=depth))
    np.testing.assert_allclose(out[:, :20], img[:, :20], atol=1e-6)  # in focus: unchanged
    assert np.std(out[:, 44:]) < 0.5 * np.std(img[:, 44:])  # far: blurred
    with pytest.raises(RuntimeError, match="needs depth"):
        apply_effects(img, eff, seed=0, ctx=_ctx())


def test_exposure_vignetting_quantize_jpeg(rng):
    img = np.full((48, 64, 3), 0.4, np.float32)
    out = apply_effects(img, _fx({"type": "exposure", "gain": 1.5, "gain_sigma_stops": 0.0, "wb_sigma": 0.0}),
                        seed=0, ctx=_ctx())
    np.testing.assert_allclose(out, 0.6, atol=1e-6)
    ctx = EffectContext("v", np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]]))
    vig = apply_effects(np.ones((48, 64, 3), np.float32), _fx({"type": "vignetting", "strength": 0.4}), seed=0, ctx=ctx)
    # Corner pixel centre (0.5, 0.5) is at r^2 = 31.5^2 + 23.5^2 of the corner's 32^2 + 24^2.
    assert vig[0, 0, 0] == pytest.approx(1 - 0.4 * (31.5**2 + 23.5**2) / (32**2 + 24**2), abs=1e-6)
    assert vig[24, 32, 0] == pytest.approx(1 - 0.4 * (0.5**2 + 0.5**2) / (32**2 + 24**2), abs=1e-6)
    x = rng.uniform(size=(16, 16, 3)).astype(np.float32)
    q = apply_effects(x, _fx({"type": "quantize", "bits": 4}), seed=0, ctx=_ctx())
    np.testing.assert_allclose(q * 15, np.round(q * 15), atol=1e-5)
    assert np.max(np.abs(q - x)) <= 0.5 / 15 + 1e-6
    smooth = np.tile(np.linspace(0, 1, 64, dtype=np.float32)[None, :, None], (48, 1, 3))
    j = apply_effects(smooth, _fx({"type": "jpeg", "quality": 90}), seed=0, ctx=_ctx())
    assert 0 < np.abs(j - smooth).mean() < 0.02  # lossy but close on a smooth ramp


@pytest.mark.parametrize("bits", [4, 8, 16])
def test_quantize_rounds_each_value_to_its_nearest_level_exactly(bits, rng):
    # The reference in exact arithmetic: a float32 value times an integer is exact in float64 (24 + 16 bits).
    x = rng.uniform(size=(300, 300, 3)).astype(np.float32)
    x[0, 0, 0] = np.float32(0.3)  # 0.3 * 15 is 4.50000018 in float64: level 5 at 4 bits
    levels = 2**bits - 1
    q = apply_effects(x, _fx({"type": "quantize", "bits": bits}), seed=0, ctx=_ctx())
    expected = (np.rint(x.astype(np.float64) * levels) / levels).astype(np.float32)
    np.testing.assert_array_equal(q, expected)


def test_random_streams_depend_only_on_seed_view_and_index():
    img = np.full((32, 32, 3), 0.5, np.float32)
    g = {"type": "gaussian", "sigma": 0.1, "clip": False}
    a = apply_effects(img, _fx(g), seed=5, ctx=_ctx("view_003"))
    b = apply_effects(img, _fx(g), seed=5, ctx=_ctx("view_003"))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, apply_effects(img, _fx(g), seed=6, ctx=_ctx("view_003")))
    assert not np.array_equal(a, apply_effects(img, _fx(g), seed=5, ctx=_ctx("view_004")))
    # Appending an effect does not change the noise drawn by the first one.
    two = apply_effects(img, _fx(g, {"type": "exposure", "gain_sigma_stops": 0.0, "wb_sigma": 0.0}), seed=5,
                        ctx=_ctx("view_003"))
    np.testing.assert_allclose(two, a, atol=1e-7)
    r = effect_rng(5, "view_003", 0).normal(size=3)
    np.testing.assert_array_equal(r, effect_rng(5, "view_003", 0).normal(size=3))


def test_effects_never_modify_their_input():
    img = np.full((16, 16, 3), 0.5, np.float32)
    before = img.copy()
    apply_effects(img, _fx({"type": "gaussian", "sigma": 0.1}, {"type": "vignetting"}), seed=0, ctx=_ctx())
    np.testing.assert_array_equal(img, before)


@pytest.mark.parametrize(("table", "key"), [
    ({"type": "gaussian"}, "effects[0].sigma"),  # neither sigma nor sigma_8bit
    ({"type": "gaussian", "sigma": 0.1, "sigma_8bit": 2.0}, "effects[0].sigma"),  # both
    ({"type": "gaussian", "sigma": -0.1}, "effects[0].sigma"),
    ({"type": "jpeg", "quality": 0}, "effects[0].quality"),
    ({"type": "jpeg", "quality": 90.5}, "effects[0].quality"),
    ({"type": "jpeg", "qualty": 90}, "effects[0].qualty"),
    ({"type": "blurr"}, "effects[0].type"),
    ({"sigma": 0.1}, "effects[0].type"),
])
def test_bad_effect_parameters_name_the_key(table, key):
    with pytest.raises(ConfigError) as info:
        parse_effect(table, key="effects[0]", path=None)
    assert info.value.key == key

"""Procedural textures and the noise kernel against slow, obvious references."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from data_synth.noise import CHANNELS, VOLUME_SIZE, apply_affine, fbm, noise_volume, octave_affine, sample_volume
from data_synth.spec import TextureSpec
from data_synth.textures import color_ramp, evaluate_texture, pattern_value


def test_sample_volume_matches_scipy_trilinear(rng):
    pts = rng.uniform(-3 * VOLUME_SIZE, 3 * VOLUME_SIZE, size=(5000, 3)).astype(np.float32)
    fast = sample_volume(pts)
    vol = noise_volume()
    for c in range(CHANNELS):
        # map_coordinates indexes [z, y, x]; grid-wrap = periodic with voxel centres at integers.
        ref = ndimage.map_coordinates(vol[..., c], pts[:, ::-1].T.astype(np.float64), order=1, mode="grid-wrap")
        # OpenCV's bilinear weights are fixed point (1/32 steps): error <= ~1/64 of the local
        # voxel-to-voxel difference (values have unit std, neighbours differ by < 1): 0.01.
        np.testing.assert_allclose(fast[:, c], ref, atol=0.01)
        assert np.mean(np.abs(fast[:, c] - ref)) < 2e-3  # typical error is far smaller


def test_noise_statistics_and_channel_independence(rng):
    vol = noise_volume()
    assert vol.shape == (VOLUME_SIZE,) * 3 + (CHANNELS,)
    # Normalised in float32 over 262k voxels: exact to ~1e-4 (float32 accumulation).
    np.testing.assert_allclose(vol.mean(axis=(0, 1, 2)), 0, atol=1e-4)
    np.testing.assert_allclose(vol.std(axis=(0, 1, 2)), 1, atol=1e-4)
    corr = np.corrcoef(vol.reshape(-1, CHANNELS).T)
    assert np.max(np.abs(corr - np.eye(CHANNELS))) < 0.02  # 262k samples, ~1000 independent features


def test_fbm_is_deterministic_and_seeded(rng):
    pts = rng.uniform(-5, 5, size=(1000, 3)).astype(np.float32)
    a = fbm(pts, octaves=4, seed=1)
    np.testing.assert_array_equal(a, fbm(pts, octaves=4, seed=1))
    assert np.corrcoef(a[:, 0], fbm(pts, octaves=4, seed=2)[:, 0])[0, 1] < 0.3
    assert np.all(fbm(pts, octaves=3, ridged=True) >= 0)
    # One octave is the volume sampled at the octave's affine image of the points.
    np.testing.assert_allclose(fbm(pts, octaves=1, seed=5), sample_volume(apply_affine(pts, octave_affine(5, 0, 1.0))),
                               atol=1e-6)


def test_checker_and_stripes_against_formulas(rng):
    pts = rng.uniform(-2, 2, size=(2000, 3)).astype(np.float32)
    checker = TextureSpec(pattern="checker", scale=0.3)
    ref = (np.floor(pts / 0.3).astype(int).sum(axis=1) % 2).astype(np.float32)
    np.testing.assert_array_equal(pattern_value(checker, pts), ref)
    stripes = TextureSpec(pattern="stripes", scale=0.2, axis=(0.0, 2.0, 0.0), duty=0.25)
    phase = pts[:, 1] / 0.2
    np.testing.assert_array_equal(pattern_value(stripes, pts), (phase - np.floor(phase) >= 0.25).astype(np.float32))


def test_color_ramp_endpoints_and_midpoints():
    colors = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 1]], np.float32)
    out = color_ramp(np.array([0.0, 0.25, 0.5, 1.0, 1.5], np.float32), colors)
    np.testing.assert_allclose(out, [[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 1, 1], [1, 1, 1]], atol=1e-6)


def test_texture_has_fine_detail_in_range(rng):
    spec = TextureSpec(pattern="noise", colors=((0.2, 0.3, 0.4), (0.8, 0.7, 0.6)), scale=0.5, detail=0.4,
                       detail_scale=0.01, octaves=4)
    # Points 2 mm apart along a line: the detail layer (1 cm) varies between neighbours.
    pts = np.stack([np.arange(500) * 0.002, np.zeros(500), np.zeros(500)], axis=1).astype(np.float32)
    rgb = evaluate_texture(spec, pts)
    assert rgb.min() >= 0 and rgb.max() <= 1
    assert np.std(np.diff(rgb[:, 0])) > 0.005
    no_detail = evaluate_texture(TextureSpec(**{**spec.__dict__, "detail": 0.0}), pts)
    assert np.std(np.diff(rgb[:, 0])) > 3 * np.std(np.diff(no_detail[:, 0]))


def test_constant_texture():
    out = evaluate_texture(TextureSpec(pattern="constant", colors=((0.1, 0.2, 0.3),)), np.zeros((4, 3), np.float32))
    np.testing.assert_allclose(out, np.tile([0.1, 0.2, 0.3], (4, 1)), atol=1e-7)


@pytest.mark.parametrize("pattern", ["noise", "turbulence", "checker", "stripes"])
def test_patterns_use_the_whole_ramp(pattern, rng):
    pts = rng.uniform(-5, 5, size=(20000, 3)).astype(np.float32)
    s = pattern_value(TextureSpec(pattern=pattern, scale=0.5, warp=0.3), pts)
    assert 0 <= s.min() and s.max() <= 1
    assert np.percentile(s, 95) - np.percentile(s, 5) > 0.4  # real contrast, not a flat colour

"""Procedural solid textures: albedo as a function of the 3-D point (see `TextureSpec`).

Evaluated at surface points in the object's local frame, so the colour of a
surface point is the same in every view (exact multi-view consistency, no UV
seams). float32.
"""

from __future__ import annotations

import numpy as np

from data_synth.noise import fbm
from data_synth.spec import TextureSpec

# Offsets between the seeds of a texture's independent noise fields.
_WARP_SEED, _DETAIL_SEED = 7919, 104729
_WARP_OCTAVES = 2  # warps are smooth: more octaves cost time and look the same
_DETAIL_CHROMA = np.array([0.25, 0.0, -0.25], np.float32)  # colour part of the fine-detail modulation


def color_ramp(s: np.ndarray, colors: np.ndarray) -> np.ndarray:
    """Map s in [0, 1] to RGB by linear interpolation between evenly spaced stops.

    Args:
        s: (M,) scalars (clipped to [0, 1]).
        colors: (K, 3) stops; K == 1 gives a constant.

    Returns:
        (M, 3) float32.
    """
    colors = np.asarray(colors, dtype=np.float32)
    if colors.shape[0] == 1:
        return np.broadcast_to(colors[0], (s.shape[0], 3)).astype(np.float32)
    x = np.clip(s, 0.0, 1.0) * np.float32(colors.shape[0] - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), colors.shape[0] - 2)
    f = (x - i0)[:, None].astype(np.float32)
    return colors[i0] * (1 - f) + colors[i0 + 1] * f


def pattern_value(spec: TextureSpec, points: np.ndarray) -> np.ndarray:
    """The scalar pattern s in [0, 1] at (M, 3) local points (before the colour ramp)."""
    p = np.asarray(points, dtype=np.float32) / np.float32(spec.scale)
    if spec.warp > 0 and spec.pattern != "constant":
        # Domain warp: displace the lookup by a smooth vector noise field (three independent fields).
        octaves = min(spec.octaves, _WARP_OCTAVES)
        d01 = fbm(p, octaves=octaves, lacunarity=spec.lacunarity, gain=spec.gain, seed=spec.seed + _WARP_SEED)
        d2 = fbm(p, octaves=octaves, lacunarity=spec.lacunarity, gain=spec.gain, seed=spec.seed + _WARP_SEED + 1)
        disp = np.concatenate([d01, d2[:, :1]], axis=1)
        p = p + np.float32(spec.warp) * disp
    if spec.pattern == "constant":
        return np.zeros(p.shape[0], np.float32)
    if spec.pattern == "checker":
        cells = np.floor(p).astype(np.int64).sum(axis=1)
        return (cells & 1).astype(np.float32)
    if spec.pattern == "stripes":
        axis = np.asarray(spec.axis, dtype=np.float32)
        axis /= np.linalg.norm(axis)
        phase = p @ axis
        return (phase - np.floor(phase) >= np.float32(spec.duty)).astype(np.float32)
    ridged = spec.pattern == "turbulence"
    n = fbm(p, octaves=spec.octaves, lacunarity=spec.lacunarity, gain=spec.gain, seed=spec.seed, ridged=ridged)[:, 0]
    if ridged:
        # |noise| of unit-std noise has mean ~0.8: centre it.
        return np.clip(0.5 + np.float32(0.6 * spec.contrast) * (n - np.float32(0.6)), 0.0, 1.0)
    return np.clip(0.5 + np.float32(0.35 * spec.contrast) * n, 0.0, 1.0)


def evaluate_texture(spec: TextureSpec, points: np.ndarray) -> np.ndarray:
    """Albedo at surface points.

    Args:
        spec: the texture.
        points: (M, 3) surface points in the object's local frame, scene units.

    Returns:
        (M, 3) float32 albedo in [0, 1].
    """
    pts = np.asarray(points, dtype=np.float32)
    rgb = color_ramp(pattern_value(spec, pts), np.asarray(spec.colors, dtype=np.float32))
    if spec.detail > 0:
        q = pts / np.float32(spec.detail_scale)
        grain = fbm(q, octaves=spec.detail_octaves, gain=0.6, seed=spec.seed + _DETAIL_SEED)
        # Brightness grain (field 0) with a little colour grain along red-blue (field 1).
        mod = grain[:, :1] + grain[:, 1:2] * _DETAIL_CHROMA
        rgb = rgb * (1 + np.float32(spec.detail) * mod)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32, copy=False)

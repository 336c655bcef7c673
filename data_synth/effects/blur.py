"""Optical blur effects: defocus (disc, optionally depth-dependent) and linear motion blur.

Kernels are normalised to sum 1 and images are filtered with reflected borders,
so blur preserves the image mean (up to border effects).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_synth.effects.registry import EffectContext, register_effect
from data_synth.schema import join_key, spec_field
from mvgeo.common.deps import cv2
from mvgeo.common.errors import ConfigError

_BORDER = cv2.BORDER_REFLECT_101


def disc_kernel(radius_px: float, *, oversample: int = 8) -> np.ndarray:
    """An antialiased disc of radius `radius_px` (area coverage per pixel), normalised to sum 1.

    Returns:
        (2k+1, 2k+1) float32 with k = ceil(radius_px); [[1]] (identity) for radius 0.
    """
    if radius_px <= 0:
        return np.ones((1, 1), np.float32)
    k = math.ceil(radius_px)
    sub = (np.arange(oversample) + 0.5) / oversample - 0.5
    offs = np.arange(-k, k + 1)
    x = (offs[:, None] + sub[None, :]).ravel()
    inside = (x[:, None] ** 2 + x[None, :] ** 2) <= radius_px**2
    cover = inside.reshape(2 * k + 1, oversample, 2 * k + 1, oversample).mean(axis=(1, 3))
    return (cover / cover.sum()).astype(np.float32)


def line_kernel(length_px: float, angle_rad: float, *, samples_per_px: int = 8) -> np.ndarray:
    """A line segment of `length_px` at `angle_rad` (image x right, y down), bilinearly splatted, sum 1."""
    if length_px <= 0:
        return np.ones((1, 1), np.float32)
    k = math.ceil(length_px / 2) + 1
    size = 2 * k + 1
    kern = np.zeros((size, size), np.float64)
    m = max(2, int(math.ceil(length_px * samples_per_px)))
    s = (np.arange(m) + 0.5) / m - 0.5
    xs = k + s * length_px * math.cos(angle_rad)
    ys = k + s * length_px * math.sin(angle_rad)
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kern, (y0 + dy, x0 + dx), wgt)
    return (kern / kern.sum()).astype(np.float32)


@dataclass(frozen=True)
class DefocusParams:
    radius_px: float = spec_field(1.5, range=(0.0, 50.0),
                                  doc="blur-disc radius; with focus_depth: the radius of a point at infinity")
    focus_depth: float | None = spec_field(None, range=(1e-6, None),
                                           doc="in-focus z-depth (scene units); unset: uniform blur, no depth needed")
    max_radius_px: float = spec_field(16.0, range=(0.0, 50.0), doc="cap on the depth-dependent radius")
    radius_step_px: float = spec_field(0.25, range=(0.05, 5.0), doc="depth-dependent: radius quantisation step")

    def validated(self, *, key: str, path: Path | None) -> DefocusParams:
        if self.focus_depth is not None and self.max_radius_px <= 0:
            raise ConfigError("must be positive with focus_depth", key=join_key(key, "max_radius_px"), path=path)
        return self


def _needs_depth(p: DefocusParams) -> frozenset[str]:
    return frozenset({"depth"}) if p.focus_depth is not None else frozenset()


@register_effect("defocus_blur", DefocusParams, needs=_needs_depth)
def defocus_blur(image: np.ndarray, params: DefocusParams, ctx: EffectContext, rng: np.random.Generator) -> np.ndarray:
    """Defocus: a disc blur; thin-lens radius r(z) = radius_px * |1 - focus_depth / z| when focus_depth is set."""
    if params.focus_depth is None:
        return cv2.filter2D(image, -1, disc_kernel(params.radius_px), borderType=_BORDER)
    z = ctx.depth
    with np.errstate(divide="ignore"):
        r = params.radius_px * np.abs(1.0 - params.focus_depth / np.where(np.isfinite(z), z, np.inf))
    r = np.minimum(r, params.max_radius_px)
    # Blur at quantised radii and blend the two levels around each pixel's radius (gather approximation).
    step = params.radius_step_px
    lvl = r / step
    lo = np.floor(lvl).astype(np.int64)
    frac = (lvl - lo).astype(np.float32)[..., None]
    out = np.empty_like(image)
    cache: dict[int, np.ndarray] = {}

    def level(i: int) -> np.ndarray:
        if i not in cache:
            cache[i] = cv2.filter2D(image, -1, disc_kernel(i * step), borderType=_BORDER)
        return cache[i]

    for i in np.unique(lo):
        sel = lo == i
        out[sel] = level(int(i))[sel] * (1 - frac[sel]) + level(int(i) + 1)[sel] * frac[sel]
    return out


@dataclass(frozen=True)
class MotionParams:
    length_px: float = spec_field(3.0, range=(0.0, 100.0), doc="blur streak length")
    angle_deg: float | None = spec_field(None, range=(-360.0, 360.0),
                                         doc="streak direction (image x right, y down); unset: random per view")


@register_effect("motion_blur", MotionParams)
def motion_blur(image: np.ndarray, params: MotionParams, ctx: EffectContext, rng: np.random.Generator) -> np.ndarray:
    """Linear motion blur along a segment (a random direction per view unless angle_deg is set)."""
    angle = math.radians(params.angle_deg) if params.angle_deg is not None else rng.uniform(0, math.pi)
    return cv2.filter2D(image, -1, line_kernel(params.length_px, angle), borderType=_BORDER)

"""Small synthetic test images (numpy only, no files)."""

import numpy as np


def smooth_scene(rng: np.random.Generator, h: int = 48, w: int = 48) -> np.ndarray:
    """A piecewise-smooth RGB image in [0.1, 0.9]: colour gradients plus a few soft discs."""
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    img = np.empty((h, w, 3))
    for c in range(3):
        a, b, ph = rng.uniform(1, 4, 3)
        img[..., c] = 0.5 + 0.2 * np.sin(a * xx * 3 + ph) * np.cos(b * yy * 3)
    for _ in range(4):
        cy, cx, r = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(4, 12)
        disc = 1 / (1 + np.exp((np.hypot(np.arange(h)[:, None] - cy, np.arange(w)[None] - cx) - r) / 1.0))
        img += disc[..., None] * rng.uniform(-0.25, 0.25, 3)
    return np.clip(img, 0.1, 0.9).astype(np.float32)


def add_noise(rng: np.random.Generator, img: np.ndarray, sigma: float) -> np.ndarray:
    return np.clip(img + sigma * rng.standard_normal(img.shape), 0, 1).astype(np.float32)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.asarray(a, np.float64) - b) ** 2)))

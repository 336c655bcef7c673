"""Solid (3-D) band-limited noise, the numeric kernel of the procedural textures.

One periodic noise volume (`VOLUME_SIZE`^3 voxels x `CHANNELS` independent
channels of Gaussian-filtered white noise, each normalised to unit std) is
built once per process from a fixed seed. One lookup returns all channels.
A noise *octave* is that volume sampled trilinearly at an affine image of the
3-D point: a random rotation and offset per (texture seed, octave) and a
scale of `VOXELS_PER_FEATURE` voxels per feature. Textures therefore differ by
seed without new volumes, octaves do not share lattice axes, and the sum of
octaves does not repeat (each octave's period is `VOLUME_SIZE /
VOXELS_PER_FEATURE` = 32 features along rotated axes).

Fast path: the volume is stored as a 2-D atlas of z-slices whose 4-channel
texels hold (field 0 at z, field 0 at z + 1, field 1 at z, field 1 at z + 1),
so one `cv2.remap` (bilinear in x, y; OpenCV gathers 4-channel texels as fast
as 1-channel ones) followed by a linear blend in z gives both fields. OpenCV's
bilinear weights are fixed point (1/32 step), so values differ from exact
trilinear interpolation by at most about 1% of the noise std; the tests
compare against `scipy.ndimage.map_coordinates(order=1, mode="grid-wrap")`.

All functions are pure: the same points and seed give the same values, so a
texture evaluated at the same 3-D surface point is identical in every view.
float32 throughout (appearance, not geometry).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from mvgeo.common.deps import cv2

VOLUME_SIZE = 64
"""Voxels per side of the periodic noise volume (a power of two)."""
VOXELS_PER_FEATURE = 4.0
"""Voxels per feature (one unit of the lattice coordinates passed to `fbm`)."""
CHANNELS = 2
"""Independent noise fields per lookup."""
_VOLUME_SEED = 0x5EED
_SMOOTH_SIGMA_VOX = 1.25
_ROW = 1024  # remap maps are (rows, _ROW): cv2.remap needs sides < 32767


@functools.lru_cache(maxsize=1)
def noise_volume() -> np.ndarray:
    """The periodic noise volume, (N, N, N, CHANNELS) float32 indexed [z, y, x, c]; each channel mean 0, std 1."""
    rng = np.random.default_rng(_VOLUME_SEED)
    vol = rng.normal(size=(VOLUME_SIZE, VOLUME_SIZE, VOLUME_SIZE, CHANNELS)).astype(np.float32)
    vol = ndimage.gaussian_filter(vol, (_SMOOTH_SIGMA_VOX,) * 3 + (0,), mode="wrap")
    vol -= vol.mean(axis=(0, 1, 2))
    vol /= vol.std(axis=(0, 1, 2))
    vol.setflags(write=False)
    return vol


@functools.lru_cache(maxsize=1)
def _atlas() -> np.ndarray:
    """z-slices stacked along rows, each followed by its first row (wrap in y): (N*(N+1), N, 2*C).

    Texel channels: (c0 at z, c0 at z+1, c1 at z, c1 at z+1), z+1 taken periodically.
    """
    vol = noise_volume()
    nxt = np.roll(vol, -1, axis=0)  # value at z + 1
    pairs = np.stack([vol, nxt], axis=-1).reshape(vol.shape[:3] + (2 * CHANNELS,))
    atlas = np.concatenate([pairs, pairs[:, :1]], axis=1).reshape(
        VOLUME_SIZE * (VOLUME_SIZE + 1), VOLUME_SIZE, 2 * CHANNELS)
    atlas = np.ascontiguousarray(atlas)
    atlas.setflags(write=False)
    return atlas


def sample_volume(points_vox: np.ndarray) -> np.ndarray:
    """Periodic trilinear sample of `noise_volume()` (fast path).

    Args:
        points_vox: (M, 3) float32 voxel coordinates (x, y, z); voxel centres at
            integers; any real values (periodic).

    Returns:
        (M, CHANNELS) float32.
    """
    n = VOLUME_SIZE
    pts = np.asarray(points_vox, dtype=np.float32)
    m = pts.shape[0]
    rows = -(-m // _ROW)
    padded = rows * _ROW
    x = np.zeros(padded, np.float32)
    x[:m] = pts[:, 0]
    y = np.zeros(padded, np.float32)
    # Wrap y into [0, n) (x wraps through the border mode) and move it to slice floor(z).
    y[:m] = pts[:, 1]
    y[:m] -= np.float32(n) * np.floor(y[:m] * np.float32(1.0 / n))
    zi = np.floor(pts[:, 2])
    fz = (pts[:, 2] - zi)[:, None]
    y[:m] += ((zi.astype(np.int64) & (n - 1)) * (n + 1)).astype(np.float32)
    v = cv2.remap(_atlas(), x.reshape(rows, _ROW), y.reshape(rows, _ROW), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_WRAP).reshape(-1, 2 * CHANNELS)[:m]
    lo, hi = v[:, 0::2], v[:, 1::2]
    return lo + fz * (hi - lo)


@functools.lru_cache(maxsize=256)
def octave_affine(seed: int, octave: int, frequency: float) -> np.ndarray:
    """Affine map (3, 4) float32 from lattice coordinates to voxel coordinates for one octave."""
    rng = np.random.default_rng([0x0C7A, int(seed) & 0xFFFFFFFF, int(octave)])
    rot = Rotation.random(random_state=rng).as_matrix()
    offset = rng.uniform(0, VOLUME_SIZE, size=3)
    aff = np.hstack([rot * (VOXELS_PER_FEATURE * frequency), offset[:, None]]).astype(np.float32)
    aff.setflags(write=False)
    return aff


def apply_affine(points: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """`points @ A[:, :3].T + A[:, 3]` for (M, 3) float32 points (cv2.transform: fast for M x 3)."""
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if pts.shape[0] == 0:
        return pts.copy()
    return cv2.transform(pts.reshape(-1, 1, 3), affine).reshape(-1, 3)


def fbm(points: np.ndarray, *, octaves: int, lacunarity: float = 2.0, gain: float = 0.5,
        seed: int = 0, ridged: bool = False) -> np.ndarray:
    """Fractal sum of `octaves` noise layers, normalised by the sum of amplitudes.

    Args:
        points: (M, 3) lattice coordinates (scene units divided by the feature size).
        octaves: number of layers (>= 1); layer k has frequency lacunarity**k and
            amplitude gain**k.
        lacunarity: frequency ratio between successive layers.
        gain: amplitude ratio between successive layers.
        seed: each (seed, octave) has its own rotation/offset into the volume.
        ridged: sum |noise| instead of noise ("turbulence": creases, a
            foliage/crumpled look).

    Returns:
        (M, CHANNELS) float32: independent fields, each about zero-mean with std
        0.6-1 (one octave: 1) unless `ridged` (then >= 0, mean about 0.8).
    """
    pts = np.asarray(points, dtype=np.float32)
    total = np.zeros((pts.shape[0], CHANNELS), dtype=np.float32)
    amp, freq, norm = 1.0, 1.0, 0.0
    for k in range(int(octaves)):
        layer = sample_volume(apply_affine(pts, octave_affine(seed, k, freq)))
        if ridged:
            np.abs(layer, out=layer)
        total += np.float32(amp) * layer
        norm += amp
        amp *= gain
        freq *= lacunarity
    return total / np.float32(norm)

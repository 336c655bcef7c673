"""Ground-truth intrinsics and the rays of image samples (the renderer's inverse projection).

The ray of continuous pixel coordinates (u, v) (top-left pixel centre at
(0.5, 0.5), docs/conventions.md) has camera-frame direction
`(x, y, 1)` with `(x, y) = undistort((u - cx) / fx, (v - cy) / fy)`. Its
parameter along the ray is therefore the z-depth.
"""

from __future__ import annotations

import math

import numpy as np

from data_synth.spec import CameraSpec
from mvgeo.camera import Camera


def camera_from_spec(spec: CameraSpec, size_wh: tuple[int, int]) -> Camera:
    """PINHOLE (or OPENCV when `spec.distortion` is set) camera for an image of `size_wh` = (W, H).

    fx = fy = (W / 2) / tan(fov_x / 2); principal point at the image centre (W/2, H/2)
    in our convention, so resizing keeps the field of view.
    """
    w, h = int(size_wh[0]), int(size_wh[1])
    f = (w / 2.0) / math.tan(math.radians(spec.fov_x_deg) / 2.0)
    if spec.distortion is None:
        return Camera("PINHOLE", w, h, np.array([f, f, w / 2.0, h / 2.0]))
    k1, k2, p1, p2 = spec.distortion
    return Camera("OPENCV", w, h, np.array([f, f, w / 2.0, h / 2.0, k1, k2, p1, p2]))


def sample_positions(size_wh: tuple[int, int], n: int) -> np.ndarray:
    """Continuous pixel coordinates of an n x n stratified grid in every pixel.

    Returns:
        (H, n, W, n, 2) float64 (u, v): sample (i, j) of pixel (row, col) is at
        (col + (j + 0.5) / n, row + (i + 0.5) / n). n = 1 gives pixel centres.
    """
    w, h = size_wh
    sub = (np.arange(n) + 0.5) / n
    u = (np.arange(w)[None, :] + sub[:, None])  # (n, W) indexed [j, col]
    v = (np.arange(h)[:, None] + sub[None, :])  # (H, n) indexed [row, i]
    uu = np.broadcast_to(u.T[None, None, :, :], (h, n, w, n))
    vv = np.broadcast_to(v[:, :, None, None], (h, n, w, n))
    return np.stack([uu, vv], axis=-1)


def camera_rays(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame ray directions with unit z for pixel coordinates.

    Args:
        camera: intrinsics.
        uv: (..., 2) pixel coordinates, our convention.

    Returns:
        dirs_cam: (..., 3) float64 `(x, y, 1)`.
        valid: (...) bool, False where undistortion did not converge / is outside
            the lens model's valid region (those samples are treated as misses).
    """
    uv = np.asarray(uv, dtype=np.float64)
    if np.any(camera.dist):
        rays = camera.unproject(uv)
        return rays.rays_cam, rays.valid
    # pinhole: closed form, no Newton iterations on the renderer's hot path
    xy = np.stack([(uv[..., 0] - camera.cx) / camera.fx, (uv[..., 1] - camera.cy) / camera.fy], axis=-1)
    dirs = np.concatenate([xy, np.ones(uv.shape[:-1] + (1,))], axis=-1)
    return dirs, np.ones(uv.shape[:-1], dtype=bool)

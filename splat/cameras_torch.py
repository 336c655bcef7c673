"""Checks and conversions from `mvgeo.camera.Camera` + poses to the tensors the rasterizer takes."""

from __future__ import annotations

import numpy as np
import torch

from mvgeo.camera import Camera
from mvgeo.common.errors import InputError


def pinhole_K(camera: Camera, *, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """(3, 3) K of a camera whose distortion is zero.

    Raises:
        InputError: the camera has non-zero distortion (undistort the images first).
    """
    n_pinhole = 3 if camera.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL") else 4
    distortion = camera.params[n_pinhole:]
    if np.any(distortion != 0):
        raise InputError(f"camera model {camera.model} has non-zero distortion {distortion.tolist()}; "
                         "the splat rasterizer is pinhole-only",
                         fix="undistort the images and cameras first (e.g. COLMAP image_undistorter)")
    return torch.as_tensor(camera.K, dtype=dtype, device=device)


def as_cam_from_world(cam_from_world: np.ndarray, n: int | None = None) -> np.ndarray:
    """(N, 3, 4) float64 from (N, 3, 4) or (N, 4, 4)."""
    m = np.asarray(cam_from_world, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] not in ((3, 4), (4, 4)):
        raise InputError(f"cam_from_world must be (N, 3, 4) or (N, 4, 4), got {m.shape}")
    if n is not None and m.shape[0] != n:
        raise InputError(f"{m.shape[0]} poses for {n} images/cameras")
    if not np.isfinite(m).all():
        raise InputError("cam_from_world contains NaN or inf")
    return m[:, :3, :4].copy()


def homogeneous(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 4) -> (..., 4, 4)."""
    bottom = torch.zeros(*m.shape[:-2], 1, 4, dtype=m.dtype, device=m.device)
    bottom[..., 0, 3] = 1
    return torch.cat([m[..., :3, :4], bottom], dim=-2)

"""Render a trained model into numpy images (the pipeline's view of the renderer)."""

from __future__ import annotations

import numpy as np
import torch

from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.progress import progress
from splat.cameras_torch import as_cam_from_world, pinhole_K
from splat.gaussian_model import GaussianModel
from splat.rasterize import RasterConfig


def render_views(model: GaussianModel, cameras: list[Camera], cam_from_world: np.ndarray, *,
                 background: tuple[float, float, float] = (0.0, 0.0, 0.0), sh_degree: int | None = None,
                 config: RasterConfig | None = None) -> list[np.ndarray]:
    """Render one image per camera.

    Args:
        model: the Gaussians.
        cameras: N pinhole cameras (zero distortion).
        cam_from_world: (N, 3, 4) or (N, 4, 4) float64 world-to-camera.
        background: RGB behind the Gaussians.
        sh_degree: SH degree to use (default: the model's maximum).
        config: rasterizer options.

    Returns:
        N float32 HxWx3 RGB arrays in [0, 1] (clipped).
    """
    poses = as_cam_from_world(cam_from_world, len(cameras))
    dev, dt = model.means.device, model.means.dtype
    bg = torch.tensor(background, dtype=dt, device=dev)
    out = []
    with torch.no_grad():
        for cam, pose in progress(list(zip(cameras, poses, strict=True)), desc="render"):
            if not isinstance(cam, Camera):
                raise InputError(f"expected mvgeo.camera.Camera, got {type(cam).__name__}")
            r = model.render(torch.as_tensor(pose, dtype=dt, device=dev), pinhole_K(cam, dtype=dt, device=dev),
                             cam.width, cam.height, sh_degree=sh_degree, background=bg, config=config)
            out.append(r.rgb.clamp(0, 1).permute(1, 2, 0).cpu().numpy().astype(np.float32))
    return out

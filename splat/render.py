"""Render a trained model into numpy images (the pipeline's view of the renderer)."""

from __future__ import annotations

import numpy as np
import torch

from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.progress import progress
from mvgeo.common.threads import torch_threads
from splat.cameras_torch import as_cam_from_world, pinhole_K
from splat.gaussian_model import GaussianModel
from splat.rasterize import RasterConfig

#: Torch's intra-op threads while rendering (the compositor keeps its own). The projection's torch ops give
#: pixels whose last float bits depend on the count (1.5e-7 between 1 and 2 threads on 256x192 views), so
#: one fixed count gives the same images on every machine and in every Ray task, and the ones training
#: renders (`splat.train.TrainConfig.torch_threads`, 1). Cost on 2 cores: 12 views at 256x192 in 0.49 s, 0.33 s
#: with 2 threads.
RENDER_TORCH_THREADS = 1


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
    with torch.no_grad(), torch_threads(RENDER_TORCH_THREADS):
        for cam, pose in progress(list(zip(cameras, poses, strict=True)), desc="render"):
            if not isinstance(cam, Camera):
                raise InputError(f"expected mvgeo.camera.Camera, got {type(cam).__name__}")
            r = model.render(torch.as_tensor(pose, dtype=dt, device=dev), pinhole_K(cam, dtype=dt, device=dev),
                             cam.width, cam.height, sh_degree=sh_degree, background=bg, config=config)
            out.append(r.rgb.clamp(0, 1).permute(1, 2, 0).cpu().numpy().astype(np.float32))
    return out

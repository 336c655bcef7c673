"""Test-time pose optimisation with frozen Gaussians (InstantSplat's evaluation protocol)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.threads import torch_threads
from mvgeo.transforms_torch import se3_exp
from splat.cameras_torch import as_cam_from_world, homogeneous, pinhole_K
from splat.gaussian_model import GaussianModel
from splat.losses import photometric_loss
from splat.rasterize import RasterConfig


@dataclass
class PoseFitConfig:
    """Adam on a left-multiplied se(3) correction `[omega, v]`.

    Attributes:
        iters: optimisation steps.
        lr: initial learning rate (radians / scene units per step scale).
        lr_final: learning rate at the last step (exponential decay).
        ssim_weight: weight of (1 - SSIM) in the loss.
        torch_threads: torch's intra-op threads while fitting (restored afterwards; the C++
            compositor keeps the caller's thread count), None = leave as is. 1 by default, as in
            `splat.train.TrainConfig` (small torch ops with 2 spinning threads were ~20x slower on a
            loaded 2-core machine; docs/benchmarks.md, splat section).
        lr_scales: one fit from the same start per scale of `lr` and `lr_final`; the pose with the lowest
            loss of all of them is returned (`fit_pose`). Adam at the full rate can overshoot and never come
            back near a view's optimum: on a DTU scan24 held-out view the 2e-3 fit kept its start (24.81 dB)
            where 5e-4 and 1e-3 reached 28.68 (docs/bench/heldout_pose_fit.md). Each scale costs one fit.
    """

    iters: int = 200
    lr: float = 2e-3
    lr_final: float = 1e-5
    ssim_weight: float = 0.2
    torch_threads: int | None = 1
    lr_scales: tuple[float, ...] = (1.0, 0.25)


def fit_pose(model: GaussianModel, image: np.ndarray, camera: Camera, cam_from_world_init: np.ndarray, *,
             iters: int | None = None, config: PoseFitConfig | None = None,
             background: tuple[float, float, float] = (0.0, 0.0, 0.0),
             raster: RasterConfig | None = None) -> np.ndarray:
    """Refine one camera pose photometrically against `image`, Gaussians frozen.

    Args:
        model: trained Gaussians (not modified).
        image: HxWx3 float32 RGB in [0, 1], the held-out view.
        camera: its intrinsics (size must match `image`).
        cam_from_world_init: (3, 4) or (4, 4) initial pose.
        iters: overrides `config.iters`.
        config: `PoseFitConfig`.

    Returns:
        (3, 4) float64 refined `cam_from_world = exp(delta) @ cam_from_world_init`: of the poses the fits
        visited (one per `config.lr_scales`; the initial one, every step's, the last), the one with the lowest
        loss against `image`; with `iters` 0 the initial pose.
        Adam with a decaying rate need not end at its best: on a DTU scan24 held-out view a 200-step fit
        ended at 17.5 dB from a start at 25.1 (500 steps reached 29.7; docs/bench/heldout_pose_fit.md).
    """
    cfg = config or PoseFitConfig()
    raster = raster or RasterConfig()
    if raster.num_threads is None:
        raster = replace(raster, num_threads=torch.get_num_threads())
    with torch_threads(cfg.torch_threads):
        return _fit_pose(model, image, camera, cam_from_world_init, iters, cfg, background, raster)


def _fit_pose(model, image, camera, cam_from_world_init, iters, cfg: PoseFitConfig, background, raster):
    n_iters = cfg.iters if iters is None else int(iters)
    img = np.asarray(image, dtype=np.float32)
    if img.shape != (camera.height, camera.width, 3):
        raise InputError(f"image shape {img.shape} does not match the camera ({camera.height}, {camera.width}, 3)")
    if not cfg.lr_scales or any(not (s > 0) for s in cfg.lr_scales):
        raise ValueError(f"PoseFitConfig.lr_scales must be one or more numbers > 0, got {cfg.lr_scales!r}")
    init = as_cam_from_world(np.asarray(cam_from_world_init)[None])[0]
    dev, dt = model.means.device, model.means.dtype
    target = torch.as_tensor(img, device=dev).permute(2, 0, 1).to(dt)
    K = pinhole_K(camera, dtype=dt, device=dev)
    base = homogeneous(torch.as_tensor(init, dtype=dt, device=dev))
    bg = torch.tensor(background, dtype=dt, device=dev)
    frozen = [p.requires_grad for p in model.parameters()]

    def loss_at(d):
        out = model.render(se3_exp(d) @ base, K, camera.width, camera.height, background=bg, config=raster)
        return photometric_loss(out.rgb, target, ssim_weight=cfg.ssim_weight, num_threads=raster.num_threads)

    if n_iters == 0:
        return init[:3].astype(np.float64)
    try:
        for p in model.parameters():
            p.requires_grad_(False)
        fits = [_adam_fit(loss_at, n_iters, cfg.lr * s, cfg.lr_final * s, dt, dev) for s in cfg.lr_scales]
    finally:
        for p, flag in zip(model.parameters(), frozen, strict=True):
            p.requires_grad_(flag)
    _, best_delta = min(fits, key=lambda f: f[0])  # the first of equal losses: the full rate's
    with torch.no_grad():
        result = (se3_exp(best_delta.double().cpu()) @ homogeneous(torch.as_tensor(init)))[:3]
    return result.numpy()


def _adam_fit(loss_at, n_iters: int, lr: float, lr_final: float, dt, dev) -> tuple[float, torch.Tensor]:
    """(lowest loss, its se(3) correction) of the poses one Adam fit from zero visits: the start, every step's
    and the last; the rate decays exponentially from `lr` to `lr_final`."""
    delta = torch.zeros(6, dtype=dt, device=dev, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, (lr_final / lr) ** (1.0 / max(n_iters, 1)))
    best_loss, best_delta = float("inf"), delta.detach().clone()
    for _ in range(n_iters):
        opt.zero_grad(set_to_none=True)
        loss = loss_at(delta)
        value = float(loss.detach())
        if value < best_loss:  # the pose this loss is of: before the step
            best_loss, best_delta = value, delta.detach().clone()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        last = float(loss_at(delta))
    if last < best_loss:  # the last pose (with no steps: the start)
        best_loss, best_delta = last, delta.detach().clone()
    return best_loss, best_delta

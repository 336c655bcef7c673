"""InstantSplat-style training: Gaussians and per-view pose corrections, jointly.

Recipe (InstantSplat / 3DGS): initialise from a coloured point cloud, Adam with
per-parameter learning rates (means decaying exponentially, scaled by the
scene extent), loss 0.8 L1 + 0.2 (1 - SSIM), one random training view per
iteration, SH degree raised every `sh_degree_interval` iterations, per-view
left-multiplied se(3) pose corrections `cam_from_world_i = exp(delta_i) @
cam_from_world_i^init` with their own decaying learning rate, densification
off by default (sparse views). Seeded and deterministic on CPU.

Optional coarse-to-fine schedule (`TrainConfig.coarse_scale`, `coarse_fraction`): the first steps
render at a reduced image size with the intrinsics rescaled to it and compare against targets
downsampled with an area filter once at setup; the remaining steps run at full size.
"""

from __future__ import annotations

import gc
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import ConfigError, InputError
from mvgeo.common.progress import progress_bar
from mvgeo.common.threads import torch_threads
from mvgeo.common.timing import StageTimer
from mvgeo.transforms_torch import se3_exp
from splat.cameras_torch import as_cam_from_world, homogeneous, pinhole_K
from splat.densify import DensifyConfig, DensifyState, accumulate, densify_and_prune
from splat.gaussian_model import GaussianModel
from splat.losses import photometric_loss, psnr
from splat.rasterize import RasterConfig

_log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Training options. Defaults follow InstantSplat (1000 iterations, poses optimised).

    Attributes:
        iters: optimisation steps (one view each).
        sh_degree: maximum SH degree 0..3.
        sh_degree_interval: the active SH degree goes up by one every this many steps.
        lr_means: initial learning rate of the means, times the scene extent.
        lr_means_final: final learning rate of the means (exponential decay), times the scene extent.
        lr_quats, lr_scales, lr_opacity, lr_sh0, lr_shN: constant learning rates (3DGS's).
        optimize_poses: learn per-view se(3) corrections.
        lr_pose, lr_pose_final: pose learning rate, decayed exponentially.
        fix_first_pose: keep view 0's pose fixed (removes the gauge freedom of moving
            the scene and all cameras together).
        ssim_weight: weight of (1 - SSIM); L1 gets 1 - ssim_weight.
        init_opacity: opacity of initial Gaussians.
        background: RGB behind the Gaussians.
        densify: adaptive density control, None = off (the sparse-view default).
        seed: seeds the view order (and densification sampling).
        raster: rasterizer options.
        log_every: record history every this many steps.
        torch_threads: torch's intra-op threads while training (restored afterwards), None = leave
            as is. 1 by default: the per-Gaussian tensors are too small to gain from more threads,
            and OpenMP workers that spin on a busy machine made steps up to 6x slower. The C++
            compositor still uses `raster.num_threads` threads (default: torch's thread count
            when training starts).
        coarse_scale: image scale of the coarse phase, in (0, 1]; 1 = no coarse phase. A view of
            W x H px renders at W' x H' = round(W * s) x round(H * s) (halves rounded up, at least
            1 px) with fx, cx scaled by W'/W and fy, cy by H'/H (exact in our pixel convention,
            where the image spans [0, W] x [0, H]), against the target area-averaged to W' x H'.
        coarse_fraction: fraction of `iters`, in [0, 1], run at `coarse_scale` (the first
            round(coarse_fraction * iters) steps); 0 = no coarse phase.
        coarse_raster: rasterizer options of the coarse steps, None = `raster`. Its `eps2d` is in
            coarse pixels: the default 0.3 px^2 there is 0.3 / s^2 full-size px^2, so Gaussians
            thinner than a pixel look wider at the coarse size than at full size.
        cuda_sync_timings: on CUDA, synchronise the device around each training sub-step so that
            `TrainResult.timings_s` can split "optimize" into sub-steps (costs the overlap of host
            and device work). Without it the sub-step keys are left out on CUDA, where host-side
            clocks would measure kernel launches only. Ignored on the CPU, where the split is
            always recorded.
    """

    iters: int = 1000
    sh_degree: int = 3
    sh_degree_interval: int = 250
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacity: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    optimize_poses: bool = True
    lr_pose: float = 1e-4
    lr_pose_final: float = 1e-6
    fix_first_pose: bool = True
    ssim_weight: float = 0.2
    init_opacity: float = 0.1
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    densify: DensifyConfig | None = None
    seed: int = 0
    raster: RasterConfig = field(default_factory=RasterConfig)
    log_every: int = 10
    torch_threads: int | None = 1
    coarse_scale: float = 1.0
    coarse_fraction: float = 0.0
    coarse_raster: RasterConfig | None = None
    cuda_sync_timings: bool = False


#: Named presets. "instantsplat": the default; "gt_poses": known poses, no pose learning;
#: "dense_views": many views, densification on; "quick": a 300-step smoke run.
TRAIN_PRESETS: dict[str, TrainConfig] = {
    "instantsplat": TrainConfig(),
    "gt_poses": TrainConfig(optimize_poses=False),
    "dense_views": TrainConfig(iters=3000, optimize_poses=False, densify=DensifyConfig(stop_iter=1500)),
    "quick": TrainConfig(iters=300, sh_degree_interval=100),
}


#: The parts of the "optimize" stage in `TrainResult.timings_s` (keys "optimize/<name>"), seconds summed
#: over the steps: "render" (pose composition and `GaussianModel.render`), "loss" (the photometric loss;
#: its C++ kernel computes the loss's gradient here too), "backward" (zeroing gradients and the backward
#: pass through the render, plus the loss's own backward on the torch path), "optimizer"
#: (learning-rate schedule and Adam step), "densify" (statistics and clone/split/prune; 0 when off),
#: "bookkeeping" (view order, history with its PSNR, progress bar), "callback" (the caller's `on_step`).
OPTIMIZE_SUBSTEPS = ("render", "loss", "backward", "optimizer", "densify", "bookkeeping", "callback")


@dataclass
class TrainHistory:
    """Per-step records (every `log_every` steps and the last).

    Attributes:
        iteration, loss, psnr_db (of the view trained on at that step, at the size it was rendered:
            reduced during a coarse phase), elapsed_s, num_gaussians.
    """

    iteration: list[int] = field(default_factory=list)
    loss: list[float] = field(default_factory=list)
    psnr_db: list[float] = field(default_factory=list)
    elapsed_s: list[float] = field(default_factory=list)
    num_gaussians: list[int] = field(default_factory=list)


@dataclass
class TrainResult:
    """Output of `train_gaussians`.

    Attributes:
        model: trained Gaussians.
        cam_from_world_optimized: (N, 3, 4) float64 poses after the learned corrections
            (equal to the input when poses are not optimised).
        history: the training curve.
        timings_s: seconds per stage: "setup", "optimize" and their sum "total"
            (`StageTimer.as_dict()`), plus the split of "optimize" into `OPTIMIZE_SUBSTEPS`
            ("optimize/render", ...; not counted again in "total", and left out on CUDA unless
            `TrainConfig.cuda_sync_timings`).
    """

    model: GaussianModel
    cam_from_world_optimized: np.ndarray
    history: TrainHistory
    timings_s: dict[str, float]


def scene_extent(cam_from_world: np.ndarray, points_xyz: np.ndarray) -> float:
    """3DGS's `cameras_extent`: 1.1 x the largest camera-centre distance from their mean,
    or the points' spread when the cameras (nearly) coincide."""
    R = cam_from_world[:, :, :3]
    centres = -np.einsum("nji,nj->ni", R, cam_from_world[:, :, 3])
    radius = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) * 1.1
    if radius < 1e-6:
        radius = float(np.linalg.norm(points_xyz - points_xyz.mean(0), axis=1).max()) if len(points_xyz) else 1.0
    return max(radius, 1e-6)


def _check_inputs(images, cameras, cam_from_world):
    if len(images) == 0:
        raise InputError("no training images")
    if len(images) != len(cameras):
        raise InputError(f"{len(images)} images but {len(cameras)} cameras")
    poses = as_cam_from_world(cam_from_world, len(images))
    for i, (img, cam) in enumerate(zip(images, cameras, strict=True)):
        if img.shape != (cam.height, cam.width, 3):
            raise InputError(f"image {i} has shape {img.shape}, camera says ({cam.height}, {cam.width}, 3)",
                             fix="pass images at the size the cameras were calibrated/rendered at")
    return poses


def _check_config(cfg: TrainConfig) -> None:
    """Raises `ConfigError` (naming the field) for coarse-schedule values out of range."""
    if not (np.isfinite(cfg.coarse_scale) and 0.0 < cfg.coarse_scale <= 1.0):
        raise ConfigError(f"got {cfg.coarse_scale}", key="coarse_scale", expected="a number in (0, 1]",
                          fix="use e.g. 0.5 for half-size coarse steps, 1 for none")
    if not (np.isfinite(cfg.coarse_fraction) and 0.0 <= cfg.coarse_fraction <= 1.0):
        raise ConfigError(f"got {cfg.coarse_fraction}", key="coarse_fraction", expected="a number in [0, 1]",
                          fix="the fraction of iterations at the coarse size, e.g. 0.5; 0 for none")


def coarse_size_wh(width: int, height: int, scale: float) -> tuple[int, int]:
    """(W', H') = (round(W * scale), round(H * scale)), halves rounded up, at least 1 px each."""
    return max(1, int(np.floor(width * scale + 0.5))), max(1, int(np.floor(height * scale + 0.5)))


def downsample_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, C) float32 image -> (height, width, C) by area averaging (each output pixel is the mean
    of the input over its footprint, fractional pixels weighted by their covered area;
    `cv2.INTER_AREA`, exact for any ratio when shrinking). Returns the input when the size is unchanged.

    Raises:
        InputError: a target size larger than the image (this filter only shrinks).
    """
    h0, w0 = image.shape[:2]
    if (width, height) == (w0, h0):
        return image
    if width > w0 or height > h0:
        raise InputError(f"downsample_area: {width}x{height} is larger than the image ({w0}x{h0})")
    return cv2.resize(np.ascontiguousarray(image, dtype=np.float32), (width, height),
                      interpolation=cv2.INTER_AREA).reshape(height, width, -1)


def _lr_at(step: int, total: int, lr0: float, lr1: float) -> float:
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return float(np.exp((1 - t) * np.log(lr0) + t * np.log(lr1)))


def train_gaussians(images: list[np.ndarray], cameras: list[Camera], cam_from_world: np.ndarray,
                    init_points_xyz: np.ndarray, init_points_rgb: np.ndarray,
                    config: TrainConfig | None = None, *, device: str | torch.device = "cpu",
                    on_step: Callable[[int, GaussianModel], None] | None = None) -> TrainResult:
    """Train Gaussians (and optionally pose corrections) on posed images.

    Args:
        images: N float32 HxWx3 RGB arrays in [0, 1].
        cameras: N pinhole cameras (sizes must match the images).
        cam_from_world: (N, 3, 4) or (N, 4, 4) initial world-to-camera poses.
        init_points_xyz: (P, 3) initial points (e.g. `mvgeo align` output).
        init_points_rgb: (P, 3) uint8 or float colours.
        config: `TrainConfig` (default: InstantSplat's recipe).
        device: torch device.
        on_step: called as `on_step(completed_steps, model)` after each step (e.g. held-out
            evaluation in benchmarks); must not modify the model.

    Returns:
        `TrainResult`.
    """
    cfg = config or TrainConfig()
    _check_config(cfg)
    if cfg.raster.num_threads is None:
        cfg = replace(cfg, raster=replace(cfg.raster, num_threads=torch.get_num_threads()))
    if cfg.coarse_raster is not None and cfg.coarse_raster.num_threads is None:
        cfg = replace(cfg, coarse_raster=replace(cfg.coarse_raster, num_threads=cfg.raster.num_threads))
    # Objects alive before training (modules, tensors of the caller) are moved out of the cyclic
    # collector's reach while training: its full passes over them took ~5% of each step (perf).
    freeze = gc.get_freeze_count() == 0
    if freeze:
        gc.freeze()
    try:
        with torch_threads(cfg.torch_threads):
            return _train(images, cameras, cam_from_world, init_points_xyz, init_points_rgb, cfg, device, on_step)
    finally:
        if freeze:
            gc.unfreeze()


def _train(images, cameras, cam_from_world, init_points_xyz, init_points_rgb, cfg: TrainConfig, device,
           on_step) -> TrainResult:
    timer = StageTimer()
    with timer.stage("setup"):
        poses = _check_inputs(images, cameras, cam_from_world)
        n_views = len(images)
        model = GaussianModel.from_points(init_points_xyz, init_points_rgb, sh_degree=cfg.sh_degree,
                                          init_opacity=cfg.init_opacity, device=device)
        extent = scene_extent(poses, np.asarray(init_points_xyz, dtype=np.float64).reshape(-1, 3))

        def as_target(im):
            return torch.as_tensor(np.ascontiguousarray(im, dtype=np.float32), device=device).permute(2, 0, 1)

        targets = [as_target(im) for im in images]
        Ks = [pinhole_K(c, device=device) for c in cameras]
        sizes_wh = [(c.width, c.height) for c in cameras]
        coarse_steps = int(np.floor(cfg.coarse_fraction * cfg.iters + 0.5)) if cfg.coarse_scale < 1.0 else 0
        if coarse_steps:
            # Targets shrunk once here; K rescaled to the rounded size (not by the nominal scale) so the
            # coarse image spans the same field of view as the full one.
            coarse_wh = [coarse_size_wh(c.width, c.height, cfg.coarse_scale) for c in cameras]
            coarse_targets = [as_target(downsample_area(im, w, h))
                              for im, (w, h) in zip(images, coarse_wh, strict=True)]
            coarse_Ks = [pinhole_K(c.scaled(w, h), device=device)
                         for c, (w, h) in zip(cameras, coarse_wh, strict=True)]
            coarse_raster = cfg.coarse_raster or cfg.raster
        base = homogeneous(torch.as_tensor(poses, dtype=torch.float32, device=device))
        bg = torch.tensor(cfg.background, dtype=torch.float32, device=device)
        deltas = torch.zeros(n_views, 6, dtype=torch.float32, device=device, requires_grad=cfg.optimize_poses)
        groups = [
            {"params": [model.means], "lr": cfg.lr_means * extent, "name": "means"},
            {"params": [model.quats], "lr": cfg.lr_quats, "name": "quats"},
            {"params": [model.log_scales], "lr": cfg.lr_scales, "name": "log_scales"},
            {"params": [model.opacity_logits], "lr": cfg.lr_opacity, "name": "opacity_logits"},
            {"params": [model.sh0], "lr": cfg.lr_sh0, "name": "sh0"},
            {"params": [model.shN], "lr": cfg.lr_shN, "name": "shN"},
        ]
        if cfg.optimize_poses:
            groups.append({"params": [deltas], "lr": cfg.lr_pose, "name": "pose"})
        # The fused kernel (one pass per parameter instead of ~10 elementwise ops) is several times faster
        # on CPU; same update rule, deterministic.
        optimizer = torch.optim.Adam(groups, eps=1e-15, fused=torch.device(device).type in ("cpu", "cuda"))
        gen = torch.Generator().manual_seed(cfg.seed)
        dstate = DensifyState.zeros(model.num_gaussians, device) if cfg.densify else None
        pose_mask = torch.ones(n_views, 1, device=device)
        if cfg.fix_first_pose:
            pose_mask[0] = 0

    # Sub-step clock: each lap adds the time since the previous lap to one bucket, so the buckets sum to
    # the loop's time (a few perf_counter calls per step, ~1 us). On CUDA the device is synchronised
    # first when asked, otherwise the split is not recorded (host clocks would time kernel launches).
    on_cuda = torch.device(device).type == "cuda"
    split = not on_cuda or cfg.cuda_sync_timings
    substep_s = dict.fromkeys(OPTIMIZE_SUBSTEPS, 0.0)
    clock = [time.perf_counter()]

    def lap(name: str) -> None:
        if on_cuda and split:
            torch.cuda.synchronize(device)
        now = time.perf_counter()
        substep_s[name] += now - clock[0]
        clock[0] = now

    history = TrainHistory()
    start = time.perf_counter()
    order: list[int] = []
    with progress_bar(desc="splat train", total=cfg.iters) as bar, timer.stage("optimize"):
        clock[0] = time.perf_counter()
        for step in range(cfg.iters):
            if not order:
                order = torch.randperm(n_views, generator=gen).tolist()
            i = order.pop()
            coarse = step < coarse_steps
            if coarse:
                (width, height), K, target, raster = coarse_wh[i], coarse_Ks[i], coarse_targets[i], coarse_raster
            else:
                (width, height), K, target, raster = sizes_wh[i], Ks[i], targets[i], cfg.raster
            degree = min(cfg.sh_degree, step // max(cfg.sh_degree_interval, 1))
            lap("bookkeeping")
            cam = se3_exp(deltas[i] * pose_mask[i]) @ base[i]
            out = model.render(cam, K, width, height, sh_degree=degree, background=bg, config=raster)
            if dstate is not None:
                out.projected.means2d.retain_grad()
            lap("render")
            loss = photometric_loss(out.rgb, target, ssim_weight=cfg.ssim_weight,
                                    num_threads=cfg.raster.num_threads)
            lap("loss")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            lap("backward")
            for group in optimizer.param_groups:
                if group["name"] == "means":
                    group["lr"] = _lr_at(step, cfg.iters, cfg.lr_means, cfg.lr_means_final) * extent
                elif group["name"] == "pose":
                    group["lr"] = _lr_at(step, cfg.iters, cfg.lr_pose, cfg.lr_pose_final)
            optimizer.step()
            lap("optimizer")
            if dstate is not None and cfg.densify is not None and step < cfg.densify.stop_iter:
                # `accumulate` scales the pixel gradient by half the larger side of the rendered image:
                # a pixel gradient at scale s is 1/s times the full-size one and the side s times, so
                # coarse and full steps add statistics in the same resolution-free units.
                accumulate(dstate, out.projected.means2d.grad, out.projected.visible, width, height)
                if step >= cfg.densify.start_iter and (step + 1) % cfg.densify.every == 0:
                    model, dstate = densify_and_prune(model, optimizer, dstate, cfg.densify, extent, gen)
                lap("densify")
            if step % cfg.log_every == 0 or step == cfg.iters - 1:
                history.iteration.append(step)
                history.loss.append(float(loss.item()))
                history.psnr_db.append(psnr(out.rgb, target))
                history.elapsed_s.append(time.perf_counter() - start)
                history.num_gaussians.append(model.num_gaussians)
                bar.set_postfix(loss=f"{loss.item():.4f}", n=model.num_gaussians)
            bar.update(1)
            lap("bookkeeping")
            if on_step is not None:
                on_step(step + 1, model)
                lap("callback")

    with torch.no_grad():
        # The pose deltas live on the training device; the poses are float64 on the CPU.
        final = se3_exp(deltas.detach().double().cpu() * pose_mask.double().cpu()) @ homogeneous(torch.as_tensor(poses))
    _log.info("trained %d Gaussians for %d steps in %.1f s", model.num_gaussians, cfg.iters,
              time.perf_counter() - start)
    timings = timer.as_dict()
    if split:
        timings.update({f"optimize/{k}": round(v, 4) for k, v in substep_s.items()})
    return TrainResult(model=model, cam_from_world_optimized=final[:, :3].cpu().numpy(), history=history,
                       timings_s=timings)


def preset(name: str, **overrides) -> TrainConfig:
    """A copy of `TRAIN_PRESETS[name]` with fields overridden.

    Raises:
        InputError: unknown preset or field name.
    """
    if name not in TRAIN_PRESETS:
        raise InputError(f"unknown training preset {name!r}", fix=f"use one of {', '.join(TRAIN_PRESETS)}")
    fields = TrainConfig.__dataclass_fields__
    bad = [k for k in overrides if k not in fields]
    if bad:
        raise InputError(f"unknown TrainConfig field(s) {bad}", fix=f"valid fields: {', '.join(fields)}")
    return replace(TRAIN_PRESETS[name], **overrides)

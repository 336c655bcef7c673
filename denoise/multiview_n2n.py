"""Multi-view Noise2Noise: neighbour views warped into view i are independent noisy targets.

With known cameras and a depth map of view i, each pixel of i is lifted to 3D,
projected into a neighbour view j and j's noisy colour is sampled there
(bilinear). Where the geometry is right, that colour is the same surface point
seen through independent sensor noise: a Noise2Noise target for view i that a
single image cannot give. Pixels are kept only where the warp is trustworthy:

- the depth of i is finite and positive, the point lies in front of j and inside j
  (between the outermost pixel centres, so that bilinear sampling stays inside);
- *depth consistency*: j's own depth at the projected pixel (nearest sample) agrees
  with the point's depth in j within `MultiViewConfig.depth_rel_tol` (relative): a
  point hidden behind something else in j (occlusion), or a wrong depth in either
  view, fails it. Without a depth map of j only the first test applies.

The target of view i is the mean of its valid warped neighbours (noise std about
``sigma / sqrt(count)``), with a per-pixel count; training (`train_multiview_n2n`)
is the plain masked mean-squared error between the network's output on noisy i and
that target on pixels with at least one valid neighbour, on the same UNet, patches,
optimiser and schedule as `denoise.n2v.train_n2v`, and the same centre-cancelling
start as `denoise.self_supervised`. Inference is one pass on the noisy image.

Limits: bilinear sampling blurs the target slightly (sub-pixel interpolation);
view-dependent effects (specularities, exposure changes) are learned as if they were
signal; the result is only as good as the depth and the poses.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from denoise.images import images_to_tensors
from denoise.model import N2VModel
from denoise.n2v import N2VConfig, StepBatch, masked_mse, new_model, optimise_unet
from denoise.patches import effective_patch_px, sample_patches
from mvgeo.common.deps import cv2
from mvgeo.common.errors import ConfigError, InputError, ShapeError

_log = logging.getLogger(__name__)

__all__ = ["MultiViewConfig", "multiview_targets", "neighbour_views", "train_multiview_n2n", "warp_view"]


#: Projections this close outside the outermost pixel centres still count as inside (rounding
#: of exactly aligned cameras; bilinear sampling replicates the border there).
_BORDER_EPS_PX = 1e-6


@dataclass(frozen=True)
class MultiViewConfig:
    """Options of the multi-view Noise2Noise targets.

    Attributes:
        neighbours: at most this many neighbour views per view (smallest angle between optical axes).
        max_angle_deg: neighbours whose optical axis turns more than this from view i's are not used.
        depth_rel_tol: depth-consistency tolerance, relative to the point's depth in the neighbour.
    """

    neighbours: int = 4
    max_angle_deg: float = 60.0
    depth_rel_tol: float = 0.01

    def __post_init__(self) -> None:
        if self.neighbours < 1:
            raise ConfigError(f"must be >= 1, got {self.neighbours}", key="neighbours")
        if not 0 < self.max_angle_deg <= 180:
            raise ConfigError(f"must be in (0, 180], got {self.max_angle_deg}", key="max_angle_deg")
        if not self.depth_rel_tol > 0:
            raise ConfigError(f"must be > 0, got {self.depth_rel_tol}", key="depth_rel_tol")


def warp_view(image_j: np.ndarray, depth_i: np.ndarray, K_i: np.ndarray, cam_i_from_world: np.ndarray,
              K_j: np.ndarray, cam_j_from_world: np.ndarray, depth_j: np.ndarray | None = None, *,
              depth_rel_tol: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Sample view j's image at the projections of view i's pixels (backward warp through i's depth).

    Args:
        image_j: ``(H_j, W_j, C)`` float image of view j.
        depth_i: ``(H_i, W_i)`` z-depth of view i (NaN / <= 0: unknown).
        K_i, K_j: ``(3, 3)`` intrinsics (our pixel convention: top-left pixel centre at (0.5, 0.5)).
        cam_i_from_world, cam_j_from_world: ``(3, 4)`` world-to-camera poses.
        depth_j: ``(H_j, W_j)`` z-depth of view j for the consistency test, or None to skip it.
        depth_rel_tol: relative depth tolerance of the consistency test.

    Returns:
        ``(warped (H_i, W_i, C) float32, valid (H_i, W_i) bool)``; invalid pixels are 0.
    """
    image_j = np.asarray(image_j, np.float32)
    if image_j.ndim != 3:
        raise ShapeError(f"image_j must be (H, W, C), got {image_j.shape}")
    depth_i = np.asarray(depth_i, np.float64)
    if depth_i.ndim != 2:
        raise ShapeError(f"depth_i must be (H, W), got {depth_i.shape}")
    h, w = depth_i.shape
    hj, wj = image_j.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([cols + 0.5, rows + 0.5, np.ones_like(cols)], axis=-1)  # (H, W, 3), our convention
    d = np.where(np.isfinite(depth_i) & (depth_i > 0), depth_i, np.nan)
    x_i = (pix @ np.linalg.inv(np.asarray(K_i, np.float64)).T) * d[..., None]
    R_i, t_i = np.asarray(cam_i_from_world, np.float64)[:, :3], np.asarray(cam_i_from_world, np.float64)[:, 3]
    R_j, t_j = np.asarray(cam_j_from_world, np.float64)[:, :3], np.asarray(cam_j_from_world, np.float64)[:, 3]
    x_w = (x_i - t_i) @ R_i  # R_i^T (x - t), row vectors
    x_j = x_w @ R_j.T + t_j
    z_j = x_j[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        uvw = x_j @ np.asarray(K_j, np.float64).T
        col_j = uvw[..., 0] / uvw[..., 2] - 0.5  # array coordinates of the projection
        row_j = uvw[..., 1] / uvw[..., 2] - 0.5
        eps = _BORDER_EPS_PX
        valid = (np.isfinite(d) & (z_j > 0) & (col_j >= -eps) & (col_j <= wj - 1 + eps) & (row_j >= -eps)
                 & (row_j <= hj - 1 + eps))
    if depth_j is not None:
        depth_j = np.asarray(depth_j, np.float64)
        if depth_j.shape != (hj, wj):
            raise ShapeError(f"depth_j must be {(hj, wj)}, got {depth_j.shape}")
        # Every pixel the bilinear sample below mixes must see the same surface: a single (nearest) depth
        # sample let an occluder's colour into 0.6 % of the pixels along its edge.
        r0 = np.floor(np.where(valid, row_j, 0)).astype(int)
        c0 = np.floor(np.where(valid, col_j, 0)).astype(int)
        for dr in (0, 1):
            for dc in (0, 1):
                dj = depth_j[np.clip(r0 + dr, 0, hj - 1), np.clip(c0 + dc, 0, wj - 1)]
                with np.errstate(invalid="ignore"):
                    valid &= np.isfinite(dj) & (np.abs(dj - z_j) <= depth_rel_tol * z_j)
    map_x = np.where(valid, col_j, -1).astype(np.float32)
    map_y = np.where(valid, row_j, -1).astype(np.float32)
    warped = cv2.remap(image_j, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    warped = warped.reshape(h, w, -1)
    warped[~valid] = 0.0
    return warped.astype(np.float32), valid


def neighbour_views(cam_from_world: np.ndarray, *, neighbours: int, max_angle_deg: float) -> list[list[int]]:
    """Per view, up to `neighbours` other views by increasing angle between optical axes (within the limit).

    Args:
        cam_from_world: ``(N, 3, 4)``.
    """
    cam = np.asarray(cam_from_world, np.float64)
    axes = cam[:, 2, :3]  # optical axis in world = third row of R
    cos = np.clip(axes @ axes.T, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    out = []
    for i in range(len(cam)):
        order = [j for j in np.argsort(ang[i], kind="stable") if j != i and ang[i, j] <= max_angle_deg]
        out.append([int(j) for j in order[:neighbours]])
    return out


def multiview_targets(images: Sequence[np.ndarray], K: np.ndarray, cam_from_world: np.ndarray,
                      depths: Sequence[np.ndarray], config: MultiViewConfig = MultiViewConfig()
                      ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The mean of the valid warped neighbours of every view, and how many were valid per pixel.

    Args:
        images: N ``(H, W, 3)`` noisy images (their sizes define the targets' grids).
        K: ``(N, 3, 3)`` intrinsics of `images`. cam_from_world: ``(N, 3, 4)``.
        depths: N ``(H, W)`` depth maps on the grids of `images` (NaN: unknown).
        config: neighbours and the consistency tolerance.

    Returns:
        Per view ``(target (H, W, 3) float32, count (H, W) int)``; target is 0 where count is 0.
    """
    n = len(images)
    K = np.asarray(K, np.float64)
    cam = np.asarray(cam_from_world, np.float64)
    if K.shape != (n, 3, 3) or cam.shape != (n, 3, 4) or len(depths) != n:
        raise InputError(f"{n} images need (N, 3, 3) K, (N, 3, 4) poses and N depth maps; got K {K.shape}, "
                         f"poses {cam.shape}, {len(depths)} depth maps")
    out = []
    for i, nbrs in enumerate(neighbour_views(cam, neighbours=config.neighbours, max_angle_deg=config.max_angle_deg)):
        h, w = images[i].shape[:2]
        acc = np.zeros((h, w, 3), np.float64)
        count = np.zeros((h, w), int)
        for j in nbrs:
            warped, valid = warp_view(images[j], depths[i], K[i], cam[i], K[j], cam[j], depths[j],
                                      depth_rel_tol=config.depth_rel_tol)
            acc += warped
            count += valid
        target = np.where(count[..., None] > 0, acc / np.maximum(count, 1)[..., None], 0.0)
        out.append((target.astype(np.float32), count))
    return out


def train_multiview_n2n(images: Sequence[np.ndarray], targets: Sequence[tuple[np.ndarray, np.ndarray]],
                        config: N2VConfig, *, seed: int = 0, model: N2VModel | None = None,
                        device: str | torch.device = "cpu") -> N2VModel:
    """Train the UNet to map each noisy view to its multi-view target (`multiview_targets`).

    Args:
        images: N ``(H, W, 3)`` noisy views in ``[0, 1]``.
        targets: N ``(target, count)`` from `multiview_targets`, on the grids of `images`.
        config: UNet and optimiser options (steps, batch, patch, lr, schedule, augmentation;
            ``method`` and the masking fields are not used).
        seed: seeds the weights and the patches.
        model: continue training this model.
        device: torch device of the training (the model is returned there).

    Returns:
        The trained `N2VModel` (``blind_spot=False``); apply it with one pass
        (`denoise.self_supervised.denoise_one_pass`).

    Raises:
        InputError: sizes disagree, or no pixel has a valid target.
    """
    tensors = images_to_tensors(images)
    if len(targets) != len(tensors):
        raise InputError(f"{len(targets)} targets for {len(tensors)} images")
    for i, ((tgt, cnt), t) in enumerate(zip(targets, tensors, strict=True)):
        if tgt.shape[:2] != tuple(t.shape[-2:]) or cnt.shape != tuple(t.shape[-2:]):
            raise InputError(f"target {i} is {tgt.shape[:2]}, image {tuple(t.shape[-2:])}")
    total = sum(int((cnt > 0).sum()) for _, cnt in targets)
    if total == 0:
        raise InputError("no pixel has a valid multi-view target",
                         fix="check the depth maps and poses, or raise depth_rel_tol")
    _log.info("multi-view targets cover %.1f %% of the pixels",
              100.0 * total / sum(t.shape[-1] * t.shape[-2] for t in tensors))
    rng = np.random.default_rng(seed)
    if model is None:
        model = new_model(config, tensors, seed=seed)
    model.blind_spot = False
    device = torch.device(device)
    model.unet.to(device)
    patch = effective_patch_px(tensors, config.patch_px)
    mean = torch.tensor(model.mean).reshape(3, 1, 1)
    std = torch.tensor(model.std).reshape(3, 1, 1)
    normed = [((t - mean) / std).to(device) for t in tensors]
    paired = [torch.cat([(torch.from_numpy(np.ascontiguousarray(tgt.transpose(2, 0, 1))) - mean) / std,
                         torch.from_numpy((cnt > 0).astype(np.float32))[None]], dim=0).to(device)
              for tgt, cnt in targets]
    def target_loss(unet: torch.nn.Module, batch: torch.Tensor, extra: torch.Tensor) -> torch.Tensor:
        return masked_mse(batch + model.alpha * unet(batch), extra[:, :3], extra[:, 3:4] > 0.5)

    def step_batch(step: int) -> StepBatch:
        return StepBatch(sample_patches(normed, patch_px=patch, batch_size=config.batch_size, rng=rng,
                                        paired=paired, augment=config.augment), target_loss)

    return optimise_unet(model, config, step_batch, desc="multiview-n2n")

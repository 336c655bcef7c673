"""The splat training the product's splat and fuse stages share (`train_splat`), and the splat's targets
with the noisy photos' finest band taken back (`noisy_detail_targets`)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from denoise.detail import NoisyDetail, noisy_detail_target, noisy_detail_weight  # numpy and cv2 only
from eval.pipeline.stage_settings import FuseStageSettings, SplatStageSettings
from eval.pipeline.views import read_views
from mvgeo.sparse_model import read_sparse_model

__all__ = ["noisy_detail_targets", "train_splat"]


def train_splat(images_dir: Path, align_dir: Path, s: SplatStageSettings | FuseStageSettings,
                 noisy_dir: Path | None = None):
    """(training result, alignment's sparse model, view stems): a splat on `images_dir`'s views,
    initialised from the alignment in `align_dir`; with `noisy_dir` (and `s.noisy_detail.weight > 0`)
    its targets take back the noisy photos' finest band (`denoise.detail.noisy_detail_target`)."""
    from splat.train import train_gaussians

    sparse = read_sparse_model(align_dir / "sparse" / "0")
    pts = np.load(align_dir / "points.npz")
    stems = [n.rsplit(".", 1)[0] for n in sparse.names]
    images = read_views(images_dir, stems)
    weights = None
    if noisy_dir is not None:
        images, weights = noisy_detail_targets(images, read_views(noisy_dir, stems), s.noisy_detail)
    cameras = [sparse.camera_of(n) for n in sparse.names]
    cam_from_world = np.stack([sparse.image(n).cam_from_world for n in sparse.names])
    res = train_gaussians(list(images.values()), cameras, cam_from_world, pts["xyz"], pts["rgb"], s.train,
                          device=s.device)
    return res, sparse, stems, weights


def noisy_detail_targets(images: Mapping[str, np.ndarray], noisy: Mapping[str, np.ndarray], detail: NoisyDetail
                         ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """(stem -> the splat's target, stem -> the weight it took): each view's `noisy_detail_target`, its weight
    scaled by the noisy photo's noise std as the denoiser estimates it (`r2r_noise_std`; a per-pixel map's
    median, as `report.md` states it)."""
    from denoise.self_supervised import r2r_noise_std

    targets, weights = {}, {}
    for k, img in images.items():
        sigma = r2r_noise_std(noisy[k])
        sigma = float(sigma.median()) if not isinstance(sigma, float | int) else float(sigma)
        weights[k] = noisy_detail_weight(detail, sigma)
        targets[k] = noisy_detail_target(img, noisy[k], detail, sigma)
    return targets, weights

"""PSNR, SSIM and LPIPS of rendered or denoised images against references.

Works on the project's numpy images (H x W x 3 float32 RGB in [0, 1], see
docs/conventions.md); the per-metric functions take torch batches: PSNR and
SSIM from `mvgeo.image_metrics` (the project's one implementation, shared with
the splatting and denoising losses), LPIPS from `eval.lpips`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from eval.lpips import lpips
from mvgeo.common.errors import ShapeError
from mvgeo.common.threads import torch_threads
from mvgeo.image_metrics import psnr, ssim_per_image

__all__ = ["ImageScores", "score_images"]


@dataclass(frozen=True)
class ImageScores:
    """Per-image scores, in the order the images were given.

    Attributes:
        psnr_db: (N,) PSNR in dB (`inf` for identical images).
        ssim: (N,) mean SSIM.
        lpips: (N,) LPIPS-AlexNet v0.1 distance (lower is better).
    """

    psnr_db: np.ndarray
    ssim: np.ndarray
    lpips: np.ndarray

    def mean(self) -> dict[str, float]:
        """Means over images: `{"psnr_db", "ssim", "lpips"}`.

        The PSNR mean is the mean of per-image dB values (the NeRF/3DGS
        convention), not the PSNR of the pooled MSE.
        """
        return {"psnr_db": float(np.mean(self.psnr_db)), "ssim": float(np.mean(self.ssim)),
                "lpips": float(np.mean(self.lpips))}


def _to_batch(img: np.ndarray, name: str) -> torch.Tensor:
    arr = np.asarray(img)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ShapeError(f"{name}: expected an (H, W, 3) image, got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):  # 8-bit values scored as [0, 1] ones: PSNR off by 48 dB
        raise TypeError(f"{name}: expected a float image in [0, 1], got {arr.dtype} (divide by 255 or 65535 first, "
                        "or read it with `mvgeo.common.imageio.read_image`)")
    return torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32)).permute(2, 0, 1)[None]


#: Torch's threads while scoring. LPIPS's network gives scores whose last float bits depend on the thread
#: count (1.5e-8 between 1 and 2 threads, on 128x96 held-out views): one fixed count gives the same score
#: on every machine and in every Ray task (docs/cluster.md). Cost: 0.21 s per 512x384 view, 0.16 s with 2.
SCORING_THREADS = 1


def score_images(preds: Sequence[np.ndarray], targets: Sequence[np.ndarray], *,
                 with_lpips: bool = True) -> ImageScores:
    """Score each `preds[i]` against `targets[i]`.

    Args:
        preds: images (H_i, W_i, 3) float in [0, 1] (renders are not clipped
            here; clip them first if the method would).
        targets: reference images, same sizes as `preds`.
        with_lpips: compute LPIPS (needs H, W >= 31); NaN otherwise.

    Returns:
        `ImageScores` with one value per pair.

    Raises:
        ShapeError: different counts or sizes.
        TypeError: an integer image (scored as [0, 1] values it would be meaningless).
    """
    if len(preds) != len(targets):
        raise ShapeError(f"preds and targets: {len(preds)} vs {len(targets)} images")
    p_db, s, lp = [], [], []
    with torch.no_grad(), torch_threads(SCORING_THREADS):
        for i, (p, t) in enumerate(zip(preds, targets, strict=True)):
            pb, tb = _to_batch(p, f"preds[{i}]"), _to_batch(t, f"targets[{i}]")
            if pb.shape != tb.shape:
                raise ShapeError(f"preds[{i}] {tuple(p.shape)} and targets[{i}] {tuple(t.shape)} differ in size")
            p_db.append(float(psnr(pb, tb)[0]))
            s.append(float(ssim_per_image(pb, tb)[0]))
            lp.append(float(lpips(pb, tb)[0]) if with_lpips else float("nan"))
    return ImageScores(np.asarray(p_db), np.asarray(s), np.asarray(lp))

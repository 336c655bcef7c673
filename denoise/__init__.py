"""Noise2Void denoising (round 1), the round-2 joint loss and fine-tuning, and view selection.

Python API (what the pipeline calls)::

    from denoise import (N2VConfig, n2v_preset, train_n2v, denoise_images,
                         Round2Config, finetune_round2, select_views,
                         save_checkpoint, load_checkpoint)

    model = train_n2v(noisy, n2v_preset("default"), seed=0)   # noisy: list of (H, W, 3) float32 [0, 1]
    clean1 = denoise_images(model, noisy, passes=8)           # K maskings averaged; passes=0: one plain pass
                                                              # (+ fusion with the centre pixel: denoise.fusion)
    sel = select_views(cam_from_world_by_name, images_by_name, k=12, seed=0)
    model = finetune_round2(model, [noisy[i] for i in idx], renders, Round2Config(), seed=0)
    clean2 = denoise_images(model, noisy, passes=8)
    save_checkpoint("model.pt", model); model = load_checkpoint("model.pt")

Layers: `filters` / `losses` / `masking` / `fusion` (torch kernels) -> `unet`, `model` ->
`n2v` (round-1 training), `inference`, `round2`, `view_selection` (+ `kmeans`) -> `cli`.
`denoise.losses.ssim` is the project's SSIM (splatting loss and evaluation metric).
"""

import mvgeo.common.deps  # noqa: F401  (cv2 before pycolmap: docs/conventions.md)

# isort: split

from denoise.inference import denoise_images
from denoise.model import N2VModel, load_checkpoint, save_checkpoint
from denoise.n2v import N2V_PRESETS, N2VConfig, n2v_preset, train_n2v
from denoise.round2 import Round2Config, finetune_round2, joint_loss
from denoise.unet import UNet, UNetConfig
from denoise.view_selection import Selection, select_views

__all__ = [
    "N2VConfig", "N2VModel", "N2V_PRESETS", "Round2Config", "Selection", "UNet", "UNetConfig",
    "denoise_images", "finetune_round2", "joint_loss", "load_checkpoint", "n2v_preset",
    "save_checkpoint", "select_views", "train_n2v",
]

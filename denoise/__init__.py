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
SSIM comes from `mvgeo.image_metrics`, shared with the splatting loss and the evaluation.
"""

import importlib

#: Public name -> the module defining it. Loaded on first access (PEP 562), so `import denoise`
#: (and the `denoise` command line, which sets the OpenMP policy before torch loads) stays light.
_EXPORTS = {
    "denoise_images": "denoise.inference",
    "N2VModel": "denoise.model", "load_checkpoint": "denoise.model", "save_checkpoint": "denoise.model",
    "N2V_PRESETS": "denoise.n2v", "N2VConfig": "denoise.n2v", "n2v_preset": "denoise.n2v",
    "train_n2v": "denoise.n2v",
    "TrainingRestart": "denoise.training_restart",
    "Round2Config": "denoise.round2", "finetune_round2": "denoise.round2", "joint_loss": "denoise.round2",
    "UNet": "denoise.unet", "UNetConfig": "denoise.unet",
    "Selection": "denoise.view_selection", "select_views": "denoise.view_selection",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])

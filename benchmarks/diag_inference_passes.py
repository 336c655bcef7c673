"""Inference passes K of the pipeline's two N2V uses, on a finished `denoise-gs eval` run of the demo:
round 1 (`denoise` stage: `denoise_with_method` on all training photos with round 1's network) and
round 2 (`refine` stage: `denoise_images(..., fuse=True)` on the selected photos with the fine-tuned
network). PSNR/SSIM/LPIPS against the clean photos, seconds per image; K=0 is one unmasked pass.
argv[1]: the run folder (.../runs/llff_like/seed0/n2v_fused), argv[2]: the clean images folder,
argv[3]: the run's preset (default "fast").

Usage: .venv/bin/python benchmarks/diag_inference_passes.py RUN CLEAN_DIR [PRESET]"""
import sys  # noqa: I001  (eval.cli sets the thread policy before torch loads)
import time
from pathlib import Path

import eval.cli  # noqa: F401  thread policy before torch
import torch

from denoise.inference import denoise_images
from denoise.model import load_checkpoint
from denoise.self_supervised import denoise_with_method
from eval.image_metrics import score_images
from eval.pipeline import preset
from eval.pipeline.stage_settings import n2v_config, stage_seed
from eval.pipeline.summaries import SelectionFile
from eval.pipeline.views import read_views

run, clean_dir = Path(sys.argv[1]), Path(sys.argv[2])
cfg = preset(sys.argv[3] if len(sys.argv) > 3 else "fast")
noisy = read_views(run / "inputs")
clean = read_views(clean_dir, list(noisy))
sel = SelectionFile.read(run / "round2" / "selection.json").names
print(f"torch threads {torch.get_num_threads()}; {len(noisy)} round-1 views, {len(sel)} round-2 views")
m1 = load_checkpoint(run / "round1" / "n2v_model.pt")
m2 = load_checkpoint(run / "round2" / "n2v_model.pt")
n2v = n2v_config(cfg.denoise)
for K in (0, 1, 2, 8):
    for label, fn, names in (
        ("round1", lambda imgs, K=K: denoise_with_method(m1, imgs, n2v, passes=K, seed=stage_seed(0, 1, "denoise")),
         list(noisy)),
        ("round2", lambda imgs, K=K: denoise_images(m2, imgs, passes=K, seed=stage_seed(0, 2, "refine"), fuse=True),
         sel)):
        imgs = [noisy[n] for n in names]
        fn(imgs[:1])  # warm-up
        t0 = time.perf_counter()
        out = fn(imgs)
        dt = (time.perf_counter() - t0) / len(imgs)
        sc = score_images(out, [clean[n] for n in names]).mean()
        print(f"{label} K={K}: PSNR {sc['psnr_db']:.3f} SSIM {sc['ssim']:.4f} LPIPS {sc['lpips']:.4f} "
              f"{dt:.3f} s/image", flush=True)

"""Round 2's noisy-photo renders, fused and denoised images of finished runs against the clean photos
(training views).

Usage: .venv/bin/python benchmarks/diag_fused_quality.py CLEAN_DIR RUN [RUN ...]
(RUN: a pipeline folder such as OUT/runs/llff_like/seed0/n2v_fused)."""
import sys
from pathlib import Path

import eval.cli  # noqa: F401  thread policy before torch
from eval.image_metrics import score_images
from eval.pipeline.views import read_views

clean_dir = Path(sys.argv[1])
for run in sys.argv[2:]:
    rd = Path(run) / "round2"
    for what in ("noisy_renders", "fused", "denoised"):
        imgs = read_views(rd / what)
        clean = read_views(clean_dir, list(imgs))
        sc = score_images(list(imgs.values()), list(clean.values())).mean()
        print(f"{run} round2/{what:14s} PSNR {sc['psnr_db']:.2f} SSIM {sc['ssim']:.3f} "
              f"LPIPS {sc['lpips']:.3f} ({len(imgs)} views)")

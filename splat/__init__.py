"""splat: differentiable 3D Gaussian splatting on CPU (C++ compositor) or any torch device.

Layers (conventions: docs/conventions.md; gsplat is the compatibility target):

- kernels: `splat/csrc/composite.cpp` (CPU tile compositor, forward + backward; `gather.cpp` sums its
  gradient rows per Gaussian), `splat/csrc/sh.cpp` (SH colour, forward + backward), `projection.cpp`,
  `tiles.cpp` and `ssim.cpp` (the loss), built with g++ on first use into
  ~/.cache/denoise-gs/splat; the plain-torch reference of every stage (`RasterConfig(backend="torch")`);
- functional: `splat.projection.project_gaussians`, `splat.tiles.bin_gaussians`,
  `splat.composite.composite_tiles`, and the whole pipeline
  `splat.rasterize.rasterize(means, quats, scales, opacities, colors_or_sh, cam_from_world, K, W, H,
  *, sh_degree, colors_rest, background, config) -> RenderOutput(rgb [3,H,W], alpha [1,H,W], depth [1,H,W])`
  (`colors_rest`: SH bands above the DC one kept apart, as `GaussianModel` keeps them);
- classes: `splat.gaussian_model.GaussianModel` (pre-activation parameters, `from_points`),
  PLY I/O `splat.ply.write_gaussian_ply / read_gaussian_ply` (standard 3DGS layout);
- training (for the pipeline):
    * `splat.train.train_gaussians(images: list[HxWx3 float32], cameras: list[Camera],
      cam_from_world: (N,3,4), init_points_xyz: (P,3), init_points_rgb: (P,3) uint8,
      config: TrainConfig) -> TrainResult(model, cam_from_world_optimized (N,3,4), history, timings_s)`;
      presets in `splat.train.TRAIN_PRESETS` ("instantsplat" default, "gt_poses", "dense_views", "quick");
    * `splat.render.render_views(model, cameras, cam_from_world) -> list[HxWx3 float32]`;
    * `splat.pose_fit.fit_pose(model, image, camera, cam_from_world_init, *, iters) -> (3,4)`
      (test-time pose optimisation with frozen Gaussians, InstantSplat's protocol; one fit per
      `PoseFitConfig.lr_scales`, the pose of lowest loss kept);
- CLI: `splat train DATA_DIR --out OUT [--iters N] [--optimize-poses] [--init POINTS.ply|depth]`,
  `splat render MODEL_DIR --cameras SPARSE_DIR --out DIR` (`splat.cli`).
"""

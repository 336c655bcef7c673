"""Refine a finished splat's colours against the noisy photos themselves, its geometry and cameras held.

A splat trained on denoised photos inherits the denoiser's bias (detail lost the same way in every view);
the noisy photos are unbiased but noisy. With the geometry held, each Gaussian's colour is fitted to every
pixel it covers in every training view, so the noise averages out over views and pixels while the detail
the denoiser removed comes back. The noisy photos are clipped to [0, 1], so the render is compared through
the expected value of clipped Gaussian noise (`denoise.clipping.clipped_mean`) with each photo's estimated
sigma (`denoise.self_supervised.r2r_noise_std`, the estimate R2R uses).

Usage: .venv/bin/python benchmarks/diag_colour_refine.py ROUND_DIR DATASET NOISY_DIR OUT [--iters N] [--lr LR]
           [--params P[,P...]] [--loss clipped|plain]      (P: sh0, shN, opacity, scales, quats)
(ROUND_DIR: a splat trained with the true cameras: `point_cloud.ply` and `sparse/0`, e.g. the `run/round1`
of `benchmarks/diag_splat_inputs.py`; DATASET: its dataset folder; NOISY_DIR: the noisy training photos.)
Prints the held-out PSNR / SSIM / LPIPS before and after, scored as the `@gt_poses` rows.
"""
import argparse
import shutil
import time
from pathlib import Path

import numpy as np
from _common import held_out_at_true_poses

# isort: off
import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
import torch
# isort: on
from denoise.clipping import clipped_mean
from denoise.self_supervised import r2r_noise_std
from eval.pipeline.validate import validate_dataset_folder
from eval.pipeline.views import read_views
from mvgeo.sparse_model import read_sparse_model
from splat.cameras_torch import pinhole_K
from splat.ply import read_gaussian_ply, write_gaussian_ply

ap = argparse.ArgumentParser()
ap.add_argument("round_dir", type=Path)
ap.add_argument("dataset", type=Path)
ap.add_argument("noisy_dir", type=Path)
ap.add_argument("out", type=Path)
ap.add_argument("--iters", type=int, default=600)
ap.add_argument("--lr", type=float, default=2.5e-3)
ap.add_argument("--params", default="sh0")
ap.add_argument("--loss", default="clipped", choices=["clipped", "plain"])
args = ap.parse_args()
dataset = validate_dataset_folder(args.dataset)
model = read_gaussian_ply(args.round_dir / "point_cloud.ply", device="cpu")
sparse = read_sparse_model(args.round_dir / "sparse" / "0")
stems = [n.rsplit(".", 1)[0] for n in sparse.names]
noisy = read_views(args.noisy_dir, stems)
targets = [torch.from_numpy(np.ascontiguousarray(noisy[s], dtype=np.float32)).permute(2, 0, 1) for s in stems]
sigmas = [torch.as_tensor(r2r_noise_std(noisy[s]), dtype=torch.float32) for s in stems]
print("sigma /255:", " ".join(f"{float(s.mean()) * 255:.1f}" for s in sigmas), flush=True)
cams = [sparse.camera_of(n) for n in sparse.names]
Ks = [pinhole_K(c) for c in cams]
poses = [torch.as_tensor(np.vstack([sparse.image(n).cam_from_world, [0, 0, 0, 1]]), dtype=torch.float32)
         for n in sparse.names]
before = held_out_at_true_poses(args.round_dir, dataset)
print(f"before: {before['psnr_db']:.2f} / {before['ssim']:.3f} / {before['lpips']:.3f}", flush=True)

names = {"sh0": model.sh0, "shN": model.shN, "opacity": model.opacity_logits, "scales": model.log_scales,
         "quats": model.quats}
unknown = set(args.params.split(",")) - set(names)
if unknown:
    raise SystemExit(f"unknown --params {sorted(unknown)}: choose from {', '.join(names)}")
train = [names[p] for p in args.params.split(",")]
for p in (model.means, model.quats, model.log_scales, model.opacity_logits, model.sh0, model.shN):
    p.requires_grad_(any(p is q for q in train))
rates = {id(model.sh0): args.lr, id(model.shN): args.lr / 20, id(model.opacity_logits): 5e-3,
         id(model.log_scales): 5e-4, id(model.quats): 1e-4}  # a tenth of training's, but the colours'
opt = torch.optim.Adam([{"params": [p], "lr": rates[id(p)]} for p in train], eps=1e-15)
gen = torch.Generator().manual_seed(0)
order: list[int] = []
bg = torch.zeros(3)
t0 = time.perf_counter()
for step in range(args.iters):
    if not order:
        order = torch.randperm(len(stems), generator=gen).tolist()
    i = order.pop()
    out = model.render(poses[i], Ks[i], cams[i].width, cams[i].height, background=bg)
    pred = out.rgb
    if args.loss == "clipped":
        pred = clipped_mean(pred, sigmas[i])
    loss = torch.mean((pred - targets[i]) ** 2)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    if step % 100 == 0:
        print(f"step {step} loss {loss.item():.5f} ({time.perf_counter() - t0:.0f} s)", flush=True)
rd = args.out / "round1"
rd.mkdir(parents=True, exist_ok=True)
shutil.copytree(args.round_dir / "sparse", rd / "sparse", dirs_exist_ok=True)
write_gaussian_ply(rd / "point_cloud.ply", model)
after = held_out_at_true_poses(rd, dataset)
print(f"after ({args.params}, {args.loss}, {args.iters} steps, lr {args.lr}): {after['psnr_db']:.2f} / "
      f"{after['ssim']:.3f} / {after['lpips']:.3f}", flush=True)

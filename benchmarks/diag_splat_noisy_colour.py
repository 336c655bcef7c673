"""Does a colour-only fit to the noisy photos recover what the denoiser smoothed away?

A splat trained on denoised photos has the scene's geometry; its colours carry the denoiser's bias (texture
lost, contrast lowered). The noisy photos are unbiased (E[noisy] = clean), and every Gaussian is seen in
several views over several pixels, so a fit of the colours alone (positions, shapes and opacities frozen)
to the noisy photos with an L2 loss averages their noise over each Gaussian's footprint instead of
copying it. This script takes a trained splat (a `denoise-gs eval` round folder that holds
`point_cloud.ply` and its training cameras in `sparse/`), fits its SH colours to the dataset's noisy
training photos for a few hundred steps, and scores the held-out views with the true cameras as the
`@gt_poses` rows do.

Usage: .venv/bin/python benchmarks/diag_splat_noisy_colour.py ROUND_DIR DATASET OUT [--iters=N,...]
[--lr=X] [--params=sh0|sh0,shN]
"""
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
from _common import cli_option, held_out_at_true_poses

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from eval.pipeline.validate import validate_dataset_folder
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import read_sparse_model
from splat.cameras_torch import pinhole_K
from splat.ply import read_gaussian_ply, write_gaussian_ply

round_dir, dataset_dir, out = (Path(a) for a in sys.argv[1:4])
iters_list = [int(x) for x in cli_option("iters", "0,200,500").split(",")]
lr = float(cli_option("lr", "0.0025"))
names_params = cli_option("params", "sh0").split(",")
dataset = validate_dataset_folder(dataset_dir)
cams = read_sparse_model(round_dir / "sparse" / "0")
by_name = cams.cam_from_world_by_name()
stems = {Path(n).stem: n for n in by_name}
train = [stems[t] for t in dataset.train if t in stems]
targets = [torch.as_tensor(np.ascontiguousarray(read_image(dataset.root / "images" / n), np.float32)).permute(2, 0, 1)
           for n in train]
Ks = [pinhole_K(cams.camera_of(n)) for n in train]
poses = [torch.as_tensor(np.vstack([by_name[n], [0, 0, 0, 1]]), dtype=torch.float32) for n in train]
wh = [(cams.camera_of(n).width, cams.camera_of(n).height) for n in train]
print(f"| colour fit to the noisy photos ({','.join(names_params)}, lr {lr}) | PSNR | SSIM | LPIPS |\n"
      "|---|---|---|---|", flush=True)
torch.set_num_threads(2)
for iters in iters_list:
    model = read_gaussian_ply(round_dir / "point_cloud.ply")
    for name, p in model.params_dict().items():
        p.requires_grad_(name in names_params)
    opt = torch.optim.Adam([p for n, p in model.params_dict().items() if n in names_params], lr=lr, eps=1e-15)
    gen = torch.Generator().manual_seed(0)
    order: list[int] = []
    for _ in range(iters):
        if not order:
            order = torch.randperm(len(train), generator=gen).tolist()
        i = order.pop()
        rgb = model.render(poses[i], Ks[i], *wh[i], sh_degree=model.sh_degree_max).rgb
        loss = torch.mean((rgb - targets[i]) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    rd = out / f"iters{iters}"
    rd.mkdir(parents=True, exist_ok=True)
    shutil.copytree(round_dir / "sparse", rd / "sparse", dirs_exist_ok=True)
    write_gaussian_ply(rd / "point_cloud.ply", model)
    m = held_out_at_true_poses(rd, dataset)
    print(f"| {iters} steps | {m['psnr_db']:.2f} | {m['ssim']:.3f} | {m['lpips']:.3f} |", flush=True)

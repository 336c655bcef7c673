"""Recorrupted-to-Recorrupted with the neighbour views as extra inputs: does the denoiser use 12 views?

Each training photo i gets, besides its own noisy colour, its `--neighbours` nearest views (smallest angle
between optical axes) warped into its grid through a depth map of i (`denoise.multiview_n2n.warp_view`,
with the depth-consistency test), as extra input channels: per neighbour 3 colour channels (the noisy
neighbour, normalised as the view) and 1 validity channel. The network is trained with R2R on view i
alone: input ``(y_i + alpha z, warped neighbours)``, target ``y_i - z / alpha``. The neighbours' noise is
independent of both, so the loss is still, in expectation, the supervised error plus a constant: the
network learns to use the neighbours where the warp is right and to ignore them where it is not, and no
neighbour is ever a target (unlike the multi-view Noise2Noise objective, whose targets carry the warp's
errors). Inference: 8 recorrupted passes on the 8 rotations / reflections, then the clipped-noise inverse,
as `denoise.self_supervised.denoise_with_method` does for R2R. `--neighbours 0` is plain R2R through the
same loop.

Geometry: the dataset's true cameras (`sparse/0`) and `mvgeo.align.dense_stereo.stereo_depths` on the
noisy photos (each view with its 2 nearest), or `--depth clean` (stereo on the clean photos: an upper
bound on what better geometry gives).

Usage: .venv/bin/python benchmarks/diag_multiview_input.py DATASET OUT [--neighbours K] [--steps S]
           [--seed N] [--depth noisy|clean]
Prints PSNR / SSIM of the photos against `clean/` (as `diag_objective_photos.py score`) and writes them
to OUT (for `diag_splat_inputs.py ... dir:OUT`).
"""

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from denoise import self_supervised as S
from denoise.images import images_to_tensors, tensor_to_image
from denoise.inference import dihedral
from denoise.multiview_n2n import neighbour_views, warp_view
from denoise.n2v import StepBatch, n2v_preset, new_model, optimise_unet
from denoise.patches import sample_patches
from denoise.r2r import recorrupt
from eval.pipeline.views import read_views, write_views
from mvgeo.align.dense_stereo import DenseStereoConfig, stereo_depths
from mvgeo.sparse_model import read_sparse_model

sys.path.insert(0, str(Path(__file__).parent))
from diag_objective_photos import score  # noqa: E402

STEPS = 2000


def neighbour_channels(images: list[np.ndarray], K: np.ndarray, cams: np.ndarray, depths: list[np.ndarray],
                       neighbours: int) -> tuple[list[np.ndarray], float]:
    """Per view ``(H, W, 4 * neighbours)``: the warped noisy neighbours (3 channels each) and their validity."""
    nbrs = neighbour_views(cams, neighbours=neighbours, max_angle_deg=60.0)
    out, valid_share = [], []
    for i, js in enumerate(nbrs):
        h, w = images[i].shape[:2]
        ch = np.zeros((h, w, 4 * neighbours), np.float32)
        for k, j in enumerate(js):
            warped, valid = warp_view(images[j], depths[i], K[i], cams[i], K[j], cams[j], depths[j])
            ch[..., 3 * k:3 * k + 3] = warped
            ch[..., 3 * neighbours + k] = valid
            valid_share.append(valid.mean())
        out.append(ch)
    return out, float(np.mean(valid_share)) if valid_share else 0.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--neighbours", type=int, default=4)
    ap.add_argument("--steps", type=int, default=STEPS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--depth", choices=["noisy", "clean"], default="noisy")
    args = ap.parse_args()
    import torch

    train = json.loads((args.dataset / "split.json").read_text())["train"]
    stems = [Path(n).stem for n in train]
    noisy_all, clean_all = read_views(args.dataset / "images"), read_views(args.dataset / "clean")
    images = [noisy_all[s] for s in stems]
    model_gt = read_sparse_model(args.dataset / "sparse" / "0")
    K = np.stack([model_gt.camera_of(n).K for n in train])
    cams = np.stack([model_gt.image(n).cam_from_world for n in train])
    nk = args.neighbours
    t0 = time.perf_counter()
    if nk:
        src = images if args.depth == "noisy" else [clean_all[s] for s in stems]
        near = neighbour_views(cams, neighbours=2, max_angle_deg=60.0)
        pairs = sorted({(min(i, j), max(i, j)) for i, js in enumerate(near) for j in js})
        depths = stereo_depths(src, K, cams, pairs, {}, DenseStereoConfig(size_px=0)).depth
        extra, share = neighbour_channels(images, K, cams, depths, nk)
    else:
        extra, share = [np.zeros(im.shape[:2] + (0,), np.float32) for im in images], 0.0
    geo_s = time.perf_counter() - t0

    cfg = n2v_preset("default", steps=args.steps)
    cfg = replace(cfg, method="r2r", unet=replace(cfg.unet, in_channels=3 + 4 * nk))
    tensors = images_to_tensors(images)
    model = new_model(cfg, tensors, seed=args.seed)
    model.blind_spot = False
    mean = torch.tensor(model.mean).reshape(3, 1, 1)
    std = torch.tensor(model.std).reshape(3, 1, 1)

    def stack(t: torch.Tensor, e: np.ndarray) -> torch.Tensor:
        e = torch.from_numpy(np.ascontiguousarray(e.transpose(2, 0, 1)))
        cols = [((e[3 * k:3 * k + 3] - mean) / std) * e[3 * nk + k:3 * nk + k + 1] for k in range(nk)]
        return torch.cat([(t - mean) / std, *cols, e[3 * nk:]], dim=0)

    normed = [stack(t, e) for t, e in zip(tensors, extra, strict=True)]
    sig = S._sigmas(images, None, "auto")
    paired = [(torch.as_tensor(s, dtype=torch.float32) / std).expand(3, *t.shape[-2:])
              for s, t in zip(sig, tensors, strict=True)]
    rng = np.random.default_rng(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    unet = model.unet

    def loss(net: torch.nn.Module, inp: torch.Tensor, views: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
        return torch.mean((inp + model.alpha * net(torch.cat([inp, views], 1)) - tgt) ** 2)

    def step_loss(step: int) -> StepBatch:
        batch, s = sample_patches(normed, patch_px=cfg.patch_px, batch_size=cfg.batch_size, rng=rng,
                                  paired=paired, augment=cfg.augment)
        inp, tgt = recorrupt(batch[:, :3], s, alpha=cfg.r2r_alpha, generator=gen)
        return StepBatch((inp, batch[:, 3:], tgt), loss)

    t1 = time.perf_counter()
    optimise_unet(model, cfg, step_loss, desc=f"r2r+{nk} views")
    train_s = time.perf_counter() - t1
    unet.eval()
    out = []
    sig_t = [torch.as_tensor(s, dtype=torch.float32) for s in sig]
    with torch.no_grad():
        for i, x in enumerate(normed):
            x = x[None]
            acc = torch.zeros_like(x[:, :3])
            for d in range(8):
                z = torch.randn(x[:, :3].shape, generator=gen) * (sig_t[i] / std)
                xi = torch.cat([x[:, :3] + cfg.r2r_alpha * z, x[:, 3:]], 1)
                xd = dihedral(xi, d)
                pred = xd[:, :3] + model.alpha * unet(xd)
                acc += dihedral(pred, d, inverse=True)
            y = (acc / 8)[0] * std + mean
            out.append(tensor_to_image(y, like=images[i]))
    out = S._undo_clipping(images, out, sig_t, S.CLEAN_SIGMA)
    write_views(args.out, dict(zip(stems, out, strict=True)))
    photos = read_views(args.out)
    print(json.dumps({"dataset": str(args.dataset), "photos": str(args.out), "neighbours": nk,
                      "depth": args.depth, "steps": args.steps, "seed": args.seed,
                      "valid_share": round(share, 3), "geometry_s": round(geo_s, 1),
                      "training_s": round(train_s, 1), **score(args.dataset, {s: photos[s] for s in stems})},
                     indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Multi-view aggregation before the DCT Wiener step: neighbour views' noisy photos, warped into view i with a
round-1 splat's depth and poses, averaged with view i's own noisy photo where depth and the denoised photos
agree; the Wiener step then filters that average (its noise std per pixel: sigma / sqrt(observations)).

Measured on DTU scan24 at sigma 25 (docs/bench/denoise_real.md, "Neighbour views warped into the Wiener
step"): at most +0.3 dB over the single-view step; the splat's depth and poses register the views to about
22 dB (the clean photos warped into each other), far from what averaging needs.

Usage: .venv/bin/python benchmarks/diag_multiview_wiener.py RUN_DIR CLEAN_DIR [--tau 0.06] [--depth-tol 0.01]

RUN_DIR is a product run of `denoise-gs eval` (`.../seedN/product`): its `inputs/` (noisy photos at the
working size), `round1/denoised`, `round1/point_cloud.ply` and `round1/sparse/0`.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

# isort: off
import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
import torch
# isort: on

from diag_bm3d_photos import _split_psnr  # noqa: E402

from denoise.self_supervised import _undo_clipping, r2r_noise_std  # noqa: E402
from denoise.wiener import WienerConfig, dct_wiener  # noqa: E402
from mvgeo.common.imageio import read_image  # noqa: E402
from mvgeo.sparse_model import read_sparse_model  # noqa: E402
from splat.cameras_torch import pinhole_K  # noqa: E402
from splat.ply import read_gaussian_ply  # noqa: E402


def render_depths(run: Path):
    """stem -> (depth (H, W), alpha (H, W), K (3, 3), cam_from_world (4, 4)) of the round-1 splat at its poses."""
    sparse = read_sparse_model(run / "round1" / "sparse" / "0")
    model = read_gaussian_ply(run / "round1" / "point_cloud.ply", device="cpu")
    out = {}
    with torch.no_grad():
        for n in sparse.names:
            cam = sparse.camera_of(n)
            cfw = np.asarray(sparse.image(n).cam_from_world, np.float64)[:3]
            pose = np.eye(4)
            pose[:3] = cfw
            K = pinhole_K(cam, dtype=torch.float32, device="cpu")
            r = model.render(torch.as_tensor(pose, dtype=torch.float32), K, cam.width, cam.height)
            out[n.rsplit(".", 1)[0]] = (r.depth[0].numpy().astype(np.float64), r.alpha[0].numpy().astype(np.float64),
                                        K.numpy().astype(np.float64), pose)
    return out


def warp_index(geo_i, geo_j, depth_tol):
    """View j's pixel seen at each pixel of view i: (rows, cols) of the nearest pixel, the valid mask (in both
    views, both depths agree within `depth_tol`), and the bilinear corners and fractions (r0, c0, fx, fy)."""
    d_i, a_i, K_i, T_i = geo_i
    d_j, a_j, K_j, T_j = geo_j
    h, w = d_i.shape
    v, u = np.mgrid[0:h, 0:w]
    pix = np.stack([u + 0.5, v + 0.5, np.ones_like(u, float)], -1) @ np.linalg.inv(K_i).T
    X_c = pix * d_i[..., None]
    T = T_j @ np.linalg.inv(T_i)
    Y = X_c @ T[:3, :3].T + T[:3, 3]
    z = Y[..., 2]
    p = Y @ K_j.T
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    ok = (a_i > 0.9) & (d_i > 0) & (z > 0) & np.isfinite(x) & np.isfinite(y)
    ok &= (x >= 0) & (x < w) & (y >= 0) & (y < h)
    c = np.clip(np.floor(np.nan_to_num(x)).astype(int), 0, w - 1)
    r = np.clip(np.floor(np.nan_to_num(y)).astype(int), 0, h - 1)
    ok &= a_j[r, c] > 0.9
    ok &= np.abs(d_j[r, c] - z) < depth_tol * z
    # bilinear: pixel centres at +0.5
    xs, ys = np.nan_to_num(x) - 0.5, np.nan_to_num(y) - 0.5
    c0 = np.clip(np.floor(xs).astype(int), 0, w - 2)
    r0 = np.clip(np.floor(ys).astype(int), 0, h - 2)
    fx, fy = np.clip(xs - c0, 0, 1), np.clip(ys - r0, 0, 1)
    return r, c, ok, (r0, c0, fx, fy)


def sample(img, r, c, bil):
    """img at the warp (nearest where `bil` is None, else bilinear), and the sum of squared weights (a sample's
    noise variance over the photo's)."""
    if bil is None:
        return img[r, c], 1.0
    r0, c0, fx, fy = bil
    w00, w01, w10, w11 = (1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx
    out = (img[r0, c0] * w00[..., None] + img[r0, c0 + 1] * w01[..., None] + img[r0 + 1, c0] * w10[..., None]
           + img[r0 + 1, c0 + 1] * w11[..., None])
    return out, w00 ** 2 + w01 ** 2 + w10 ** 2 + w11 ** 2


def box3(x):
    """3 x 3 box mean."""
    from scipy.ndimage import uniform_filter
    return uniform_filter(x, size=3, mode="nearest")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("clean_dir", type=Path)
    ap.add_argument("--tau", type=float, nargs="+", default=[0.06])
    ap.add_argument("--depth-tol", type=float, default=0.01)
    ap.add_argument("--block", type=int, default=12)
    ap.add_argument("--interp", choices=["nearest", "bilinear"], default="nearest")
    ap.add_argument("--pilot", choices=["den", "mvden"], default="den")
    args = ap.parse_args()
    t0 = time.perf_counter()
    geo = render_depths(args.run)
    stems = sorted(geo)
    noisy = {s: read_image(args.run / "inputs" / f"{s}.png").astype(np.float64) for s in stems}
    den = {s: read_image(args.run / "round1" / "denoised" / f"{s}.png").astype(np.float64) for s in stems}
    sig = {s: r2r_noise_std(noisy[s].astype(np.float32)) for s in stems}
    print(f"depths in {time.perf_counter() - t0:.1f} s")
    names = [f"{s}.png" for s in stems]
    print("noisy   ", _split_psnr(dict(zip(names, noisy.values(), strict=True)), args.clean_dir))
    print("denoised", _split_psnr(dict(zip(names, den.values(), strict=True)), args.clean_dir))
    cfg = WienerConfig(block_px=args.block)
    warps = {}
    for i in stems:
        for j in stems:
            if i != j:
                warps[i, j] = warp_index(geo[i], geo[j], args.depth_tol)
    # The registration's ceiling: the clean photos warped the same way, against the clean photo of view i.
    clean = {s: read_image(args.clean_dir / f"{s}.png").astype(np.float64) for s in stems}
    for interp in ("nearest", "bilinear"):
        errs = []
        for (i, j), (r, c, ok, bil) in warps.items():
            cj, _ = sample(clean[j], r, c, bil if interp == "bilinear" else None)
            errs.append(((cj - clean[i]) ** 2).mean(-1)[ok])
        frac = np.mean([w[2].mean() for w in warps.values()])
        print(f"clean photos warped ({interp}): {10 * np.log10(1.0 / np.concatenate(errs).mean()):.2f} dB over "
              f"the {frac:.2f} of the pixels that pass the depth test")
    for tau in args.tau:
        t = time.perf_counter()
        out_mv, out_mvmean, counts = {}, {}, []
        for i in stems:
            acc_y, acc_d = noisy[i].copy(), den[i].copy()
            n = np.ones(noisy[i].shape[:2])
            var = np.full(noisy[i].shape[:2], float(sig[i]) ** 2)
            for j in stems:
                if j == i:
                    continue
                r, c, ok, bil = warps[i, j]
                bil = bil if args.interp == "bilinear" else None
                dj, _ = sample(den[j], r, c, bil)
                yj, wsq = sample(noisy[j], r, c, bil)
                agree = box3(np.abs(dj - den[i]).mean(-1)) < tau
                m = (ok & agree)[..., None]
                acc_y += np.where(m, yj, 0)
                acc_d += np.where(m, dj, 0)
                var += m[..., 0] * float(sig[j]) ** 2 * wsq
                n += m[..., 0]
            mean_y = acc_y / n[..., None]
            std = np.sqrt(var) / n
            counts.append(n.mean())
            out_mvmean[i] = (acc_d / n[..., None]).astype(np.float32)
            pilot = den[i] if args.pilot == "den" else out_mvmean[i].astype(np.float64)
            x = dct_wiener(mean_y, pilot, np.repeat(std[..., None], 3, -1), cfg)
            out_mv[i] = np.clip(x, 0, 1).astype(np.float32)
        sig_t = [torch.as_tensor(sig[s], dtype=torch.float32) for s in stems]
        fixed = _undo_clipping([noisy[s].astype(np.float32) for s in stems], [out_mv[s] for s in stems], sig_t, 0.0)
        print(f"tau {tau}: mean observations per pixel {np.mean(counts):.2f}; {time.perf_counter() - t:.1f} s")
        print("  mv wiener      ", _split_psnr(dict(zip(names, [np.clip(f, 0, 1) for f in fixed], strict=True)),
                                               args.clean_dir))
        print("  mv mean of den ", _split_psnr(dict(zip(names, out_mvmean.values(), strict=True)), args.clean_dir))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

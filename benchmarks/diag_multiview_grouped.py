"""The grouped Wiener step with similar patches also searched in the other views.

`denoise.grouped_wiener` groups a reference patch with the patches most like it within +-10 px of it in the
same photo. Here the candidates also include, for every other view where the round-1 splat's depth maps the
reference's centre (depth-consistent in both views), the patches within +-`--reach` px of where it lands: a
search, so a registration a few pixels off (the splat's depth registers the views to about 22 dB) still finds
the same surface. Only the estimates of view i's own patches are put back into view i.

With `--quota Q`, each other view's Q best candidates enter the group before the rest is chosen by distance.

Usage: .venv/bin/python benchmarks/diag_multiview_grouped.py RUN_DIR CLEAN_DIR [--reach -1 4] [--group 40 80]
           [--quota 0] [--views N]

RUN_DIR is a product run of `denoise-gs eval` (`.../seedN/product`); its `round1/denoised` photos (the
preset's final ones) are the pilots of both rows, the single-view row (`--reach -1`) and the multi-view one.
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
from diag_multiview_wiener import render_depths, warp_index  # noqa: E402

from denoise.clipping import clipped_mean, clipped_sides, clipped_variance  # noqa: E402
from denoise.grouped_wiener import _patch_distances, _wiener_rows, _window_sums, search_offsets  # noqa: E402
from denoise.images import image_to_tensor, tensor_to_image  # noqa: E402
from denoise.self_supervised import _undo_clipping, r2r_noise_std  # noqa: E402
from denoise.wiener import OPPONENT, block_origins  # noqa: E402
from mvgeo.common.imageio import read_image  # noqa: E402

P, RADIUS, STRIDE, CLIPPED_SHARE, CHUNK = 5, 10, 3, 0.2, 512


def prepared(noisy, den, sigma):
    """Opponent-space noisy photo, pilot and noise variance (the clipped domain where the photo is clipped)."""
    low, high = clipped_sides(noisy)
    d, std = den, np.full(noisy.shape, float(sigma))
    if low or high:
        x, s = image_to_tensor(den.astype(np.float32)), torch.as_tensor(float(sigma))
        d = tensor_to_image(clipped_mean(x, s, low=low, high=high), like=den)
        std = tensor_to_image(clipped_variance(x, s, low=low, high=high).sqrt(), like=den)
    var = np.maximum(np.asarray(std, np.float64) ** 2 @ (OPPONENT ** 2).T, 1e-6)
    return noisy.astype(np.float64) @ OPPONENT.T, np.asarray(d, np.float64) @ OPPONENT.T, var


def multiview_grouped(i, views, warps, reach, n, max_neighbours, quota=0):
    """View i's photo refined with groups drawn from its own window and the other views' (module docstring)."""
    y_i, b_i, _ = views[i]
    H, W, C = y_i.shape
    V = len(views)
    HW = H * W
    ref_y, ref_x = (a.ravel() for a in np.meshgrid(block_origins(H, P, STRIDE), block_origins(W, P, STRIDE),
                                                   indexing="ij"))
    offsets = search_offsets(RADIUS)
    K = len(offsets)
    dist_own = _patch_distances(b_i, ref_y, ref_x, P, offsets)
    dist_own[:, K // 2] = -1.0
    # Every view's arrays stacked: a patch origin is view * HW + row * W + col.
    y_f = torch.from_numpy(np.concatenate([v[0].reshape(HW, C) for v in views]).astype(np.float32))
    b_f = torch.from_numpy(np.concatenate([v[1].reshape(HW, C) for v in views]).astype(np.float32))
    v_win, c_win = np.zeros((V, H, W, C)), np.zeros((V, H, W))
    for k, (y, _, var) in enumerate(views):
        for c in range(C):
            v_win[k, :H - P + 1, :W - P + 1, c] = _window_sums(var[..., c], P) / (P * P)
        rgb = y @ OPPONENT
        clipped = ((rgb <= 1e-6) | (rgb >= 1 - 1e-6)).sum(axis=2).astype(np.float64)
        c_win[k, :H - P + 1, :W - P + 1] = _window_sums(clipped, P)
    v_f = torch.from_numpy(v_win.reshape(V * HW, C).astype(np.float32))
    c_f = torch.from_numpy(c_win.reshape(V * HW))
    dy, dx = np.meshgrid(np.arange(P), np.arange(P), indexing="ij")
    within = torch.from_numpy(dy.ravel() * W + dx.ravel())
    d = P * P * C
    # Own candidates' flat origins (view i).
    own_origin = (i * HW + (ref_y[:, None] + offsets[:, 0]) * W + ref_x[:, None] + offsets[:, 1])
    # Neighbour candidates: the reference's centre warped into view j, +-reach around it.
    near = search_offsets(reach) if reach >= 0 else np.zeros((0, 2), int)
    neigh = []
    if reach >= 0:
        others = sorted((j for j in range(V) if j != i), key=lambda j: -warps[i, j][2].mean())[:max_neighbours]
        cy, cx = ref_y + P // 2, ref_x + P // 2
        for j in others:
            r, c, ok, _ = warps[i, j]
            oy = r[cy, cx][:, None] - P // 2 + near[:, 0]
            ox = c[cy, cx][:, None] - P // 2 + near[:, 1]
            valid = ok[cy, cx][:, None] & (oy >= 0) & (oy <= H - P) & (ox >= 0) & (ox <= W - P)
            neigh.append((j * HW + np.clip(oy, 0, H - P) * W + np.clip(ox, 0, W - P), valid))
    cand = np.concatenate([own_origin] + [o for o, _ in neigh], axis=1) if neigh else own_origin
    num = torch.zeros((HW, C), dtype=torch.float64)
    den = torch.zeros(HW, dtype=torch.float64)
    n_from_others = 0
    for c0 in range(0, len(ref_y), CHUNK):
        rows = slice(c0, c0 + CHUNK)
        dist = torch.from_numpy(dist_own[rows].astype(np.float32))
        if neigh:
            ref = b_f[(torch.from_numpy(own_origin[rows, K // 2])[:, None] + within)]  # (r, p^2, C)
            parts = [dist]
            for o, valid in neigh:
                org = torch.from_numpy(o[rows])
                pt = b_f[(org[:, :, None] + within)]  # (r, k, p^2, C)
                dd = ((pt - ref[:, None]) ** 2).sum(dim=(2, 3))
                dd[~torch.from_numpy(valid[rows])] = float("inf")
                if quota > 0:  # each view's best matches enter the group first (finite ones only)
                    best = torch.topk(dd, quota, dim=1, largest=False).indices
                    fin = torch.isfinite(torch.gather(dd, 1, best))
                    dd.scatter_(1, best, torch.where(fin, torch.full_like(best, -0.5, dtype=dd.dtype),
                                                     torch.full_like(best, float("inf"), dtype=dd.dtype)))
                parts.append(dd)
            dist = torch.cat(parts, dim=1)
        chosen = torch.topk(dist, n, dim=1, largest=False).indices
        chosen_ok = torch.isfinite(torch.gather(dist, 1, chosen))
        origin = torch.gather(torch.from_numpy(cand[rows]), 1, chosen)
        origin[~chosen_ok] = torch.from_numpy(own_origin[rows, K // 2])[:, None].expand_as(origin)[~chosen_ok]
        r = origin.shape[0]
        flat = (origin[:, :, None] + within).reshape(-1)
        Y = y_f[flat].reshape(r, n, d)
        B = b_f[flat].reshape(r, n, d)
        noise_var = v_f[origin].mean(dim=1)
        S = noise_var[:, None, :].expand(r, P * P, C).reshape(r, d)
        mean_b = B.mean(dim=1, keepdim=True)
        share = c_f[origin].sum(dim=1) / (n * d)
        mean = torch.where((share > CLIPPED_SHARE)[:, None, None], mean_b, Y.mean(dim=1, keepdim=True))
        X = mean + _wiener_rows(Y - mean, B - mean_b, S)
        mine = (origin // HW) == i  # (r, n)
        n_from_others += int((~mine).sum())
        keep = mine[:, :, None].expand(r, n, P * P).reshape(-1)
        local = flat - i * HW
        num.index_add_(0, local[keep], X.reshape(-1, C).to(torch.float64)[keep])
        den.index_add_(0, local[keep], torch.ones(int(keep.sum()), dtype=torch.float64))
    out = (num / den.clamp_min(1e-12)[:, None]).reshape(H, W, C).numpy() @ OPPONENT
    hole = (den.reshape(H, W) == 0).numpy()
    out[hole] = (b_i @ OPPONENT)[hole]
    return np.clip(out, 0, 1).astype(np.float32), n_from_others / (len(ref_y) * n)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("clean_dir", type=Path)
    ap.add_argument("--reach", type=int, nargs="+", default=[-1, 4])
    ap.add_argument("--group", type=int, nargs="+", default=[40])
    ap.add_argument("--neighbours", type=int, default=11)
    ap.add_argument("--quota", type=int, nargs="+", default=[0])
    ap.add_argument("--depth-tol", type=float, default=0.01)
    ap.add_argument("--views", type=int, default=0, help="only the first N views (0: all)")
    args = ap.parse_args()
    geo = render_depths(args.run)
    stems = sorted(geo)
    noisy = [read_image(args.run / "inputs" / f"{s}.png").astype(np.float64) for s in stems]
    den = [read_image(args.run / "round1" / "denoised" / f"{s}.png").astype(np.float64) for s in stems]
    sig = [r2r_noise_std(x.astype(np.float32)) for x in noisy]
    views = [prepared(y, dd, s) for y, dd, s in zip(noisy, den, sig, strict=True)]
    warps = {(i, j): warp_index(geo[stems[i]], geo[stems[j]], args.depth_tol)
             for i in range(len(stems)) for j in range(len(stems)) if i != j}
    todo = range(args.views or len(stems))
    names = [f"{stems[i]}.png" for i in todo]
    print("pilot (the preset's photos):", _split_psnr({nm: den[i] for nm, i in zip(names, todo, strict=True)},
                                                      args.clean_dir))
    sig_t = [torch.as_tensor(s, dtype=torch.float32) for s in sig]
    for n, reach, quota in ((n, r, q) for n in args.group for r in args.reach for q in args.quota):
        t = time.perf_counter()
        outs, shares = [], []
        for i in todo:
            o, share = multiview_grouped(i, views, warps, reach, n, args.neighbours, quota)
            outs.append(o)
            shares.append(share)
        fixed = _undo_clipping([noisy[i].astype(np.float32) for i in todo], outs, [sig_t[i] for i in todo], 0.0)
        label = "single view" if reach < 0 else f"+-{reach} px in {args.neighbours} other views, quota {quota}"
        print(f"group {n}, {label}: {np.mean(shares):.2f} of the patches from other views, "
              f"{(time.perf_counter() - t) / len(outs):.1f} s per photo:",
              _split_psnr({nm: np.clip(f, 0, 1) for nm, f in zip(names, fixed, strict=True)}, args.clean_dir))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Where the pipeline's splat quality goes: alignment cloud vs ground truth, and splat runs on one round.

Given a finished pipeline round folder (`ROUND/denoised/`, `ROUND/align/`) and the dataset it came from
(`images/`, `clean/`, `depth/`, `split.json`, `sparse/0/`), prints one JSON line per check:

- `depth`: the alignment's dense cloud registered to the truth (Sim(3) on the camera centres) and
  compared with the ground-truth depth maps: median / 90th-percentile relative depth error per view;
- `splat`: train the Gaussians on the round's images as the pipeline does (alignment poses and cloud,
  `splat.TRAIN_PRESETS["instantsplat"]` with `--iters`), score the held-out views as `denoise-gs eval`
  does, and the training views against `clean/` and against the images trained on;
  `--lr-means-x K` multiplies the position learning rates; `--oracle` trains with the ground-truth
  poses and a cloud back-projected from the ground-truth depth (the ceiling for these images); `--mix
  true-cloud` / `--mix true-poses` swap in only one of the two (which half limits the result).

Run: `.venv/bin/python benchmarks/diag_splat_init.py ROUND DATA [--iters 300] [--oracle] [--lr-means-x K]`
(e.g. ROUND = `runs/demo/eval/runs/llff_like/seed0/n2v/round1`, DATA = `runs/demo/llff_like`).
`--realign` first re-runs `mvgeo align` (the round's preset is not known here: `preview` with the
focal-prior fallback, as `make demo`) on the round's denoised images into `ROUND.realign*/`;
`--no-dense-stereo`, `--downsample voxel` and `--no-free-space` select the older cloud constructions,
`--points N` another point budget; `--train-images DIR` trains on other images than `ROUND/denoised`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import mvgeo.common.deps  # noqa: E402,F401  (cv2 before pycolmap; thread policy before torch)
from eval.evaluate import EvalConfig, _score_scene  # noqa: E402
from eval.heldout import register_sim3  # noqa: E402
from eval.pipeline.validate import validate_dataset_folder  # noqa: E402
from mvgeo.common.imageio import read_image  # noqa: E402
from mvgeo.sparse_model import read_sparse_model  # noqa: E402


def _poses(model) -> dict[str, np.ndarray]:
    return {Path(n).stem: np.asarray(model.image(n).cam_from_world)[:3] for n in model.names}


def depth_check(round_dir: Path, data: Path) -> dict:
    est, gt = read_sparse_model(round_dir / "align" / "sparse" / "0"), read_sparse_model(data / "sparse" / "0")
    sim, _ = register_sim3(_poses(est), _poses(gt))  # est_from_ref: x_est = s R x_ref + t
    xyz = ((np.load(round_dir / "align" / "points.npz")["xyz"] - sim.t) @ sim.R) / sim.scale
    rows, ratios = {}, []
    for stem in _poses(est):
        n = next(m for m in gt.names if Path(m).stem == stem)
        T, cam = np.asarray(gt.image(n).cam_from_world)[:3], gt.camera_of(n)
        fx, fy, cx, cy = cam.params
        xc = xyz @ T[:, :3].T + T[:, 3]
        xc = xc[xc[:, 2] > 0]
        u, v = fx * xc[:, 0] / xc[:, 2] + cx, fy * xc[:, 1] / xc[:, 2] + cy
        ok = (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        z_true = np.load(data / "depth" / f"{stem}.npy")[v[ok].astype(int), u[ok].astype(int)]
        fin = np.isfinite(z_true)
        rel = xc[ok][fin, 2] / z_true[fin] - 1.0
        ratios.append(rel + 1.0)
        rows[stem] = {"median_abs": round(float(np.median(np.abs(rel))), 4),
                      "median_signed": round(float(np.median(rel)), 4),
                      "p90_abs": round(float(np.percentile(np.abs(rel), 90)), 4),
                      "in_front_5pct": round(float(np.mean(rel < -0.05)), 3)}
    # The Sim(3) fitted to the camera centres fixes the scale only as well as the centres do (a
    # forward-facing rig with a small spread): the scale-free error divides out one global scale
    # (the median depth ratio over all views) and measures the cloud's shape alone.
    all_ratios = np.concatenate(ratios)
    scale = float(np.median(all_ratios))
    return {"check": "depth", "round": str(round_dir), "per_view": rows,
            "median_of_views": float(np.median([r["median_abs"] for r in rows.values()])),
            "global_depth_scale": round(scale, 4),
            "median_abs_scale_free": round(float(np.median(np.abs(all_ratios / scale - 1.0))), 4),
            "in_front_5pct_scale_free": round(float(np.mean(all_ratios / scale < 0.95)), 3)}


def splat_check(round_dir: Path, data: Path, iters: int, oracle: bool, lr_means_x: float,
                mix: str | None = None, train_images: Path | None = None) -> dict:
    from splat.train import TRAIN_PRESETS, train_gaussians

    dataset = validate_dataset_folder(data)
    gt = read_sparse_model(data / "sparse" / "0")
    sparse = read_sparse_model(round_dir / "align" / "sparse" / "0")
    names = sparse.names
    stems = [Path(n).stem for n in names]
    images = [read_image((train_images or round_dir / "denoised") / f"{s}.png") for s in stems]
    cfg = dataclasses.replace(TRAIN_PRESETS["instantsplat"], iters=iters, seed=0,
                              lr_means=TRAIN_PRESETS["instantsplat"].lr_means * lr_means_x,
                              lr_means_final=TRAIN_PRESETS["instantsplat"].lr_means_final * lr_means_x)
    if oracle:
        from splat.dataset import load_views, points_from_depth

        cams = [gt.camera_of(n) for n in names]
        cfw = np.stack([np.asarray(gt.image(n).cam_from_world)[:3] for n in names])
        xyz, rgb = points_from_depth(data, load_views(data, split="train"))
        cfg = dataclasses.replace(cfg, optimize_poses=False)
    else:
        cams = [sparse.camera_of(n) for n in names]
        cfw = np.stack([np.asarray(sparse.image(n).cam_from_world)[:3] for n in names])
        pts = np.load(round_dir / "align" / "points.npz")
        xyz, rgb = pts["xyz"], pts["rgb"]
        sim, _ = register_sim3(_poses(sparse), _poses(gt))  # x_est = s R x_ref + t
        if mix == "true-cloud":  # our cameras, the cloud back-projected from the true depth (mapped in)
            from splat.dataset import load_views, points_from_depth

            xyz, rgb = points_from_depth(data, load_views(data, split="train"))
            xyz = sim.scale * xyz @ sim.R.T + sim.t
        elif mix == "true-poses":  # the true cameras (fixed), our cloud mapped into their frame
            cams = [gt.camera_of(n) for n in names]
            cfw = np.stack([np.asarray(gt.image(n).cam_from_world)[:3] for n in names])
            xyz = ((xyz - sim.t) @ sim.R) / sim.scale
            cfg = dataclasses.replace(cfg, optimize_poses=False)
    start = time.perf_counter()
    res = train_gaussians(images, cams, cfw, xyz, rgb, cfg)
    seconds = time.perf_counter() - start
    from splat.render import render_views

    est = {s: np.asarray(res.cam_from_world_optimized[i])[:3] for i, s in enumerate(stems)}
    per_view, pose = _score_scene(res.model, gt, None if oracle or mix == "true-poses" else est, dataset,
                                  EvalConfig(), cams)
    renders = render_views(res.model, cams, np.stack([est[s] for s in stems]))
    clean = [read_image(data / "clean" / f"{s}.png") for s in stems]

    def psnr(a, b):
        return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))

    return {"check": "splat", "round": str(round_dir), "iters": iters, "oracle": oracle, "mix": mix,
            "train_images": str(train_images or round_dir / "denoised"),
            "lr_means_x": lr_means_x,
            "seconds": round(seconds, 1), "gaussians": int(len(xyz)),
            "heldout_psnr_db": float(np.mean([v["psnr_db"] for v in per_view.values()])),
            "heldout_lpips": float(np.mean([v["lpips"] for v in per_view.values()])),
            "train_render_psnr_vs_clean_db": float(np.mean([psnr(r, c) for r, c in zip(renders, clean, strict=True)])),
            "train_render_psnr_vs_input_db": float(np.mean([psnr(r, i) for r, i in zip(renders, images, strict=True)])),
            **pose}


def realign(round_dir: Path, *, dense_stereo: bool = True, downsample: str = "pixel", free_space: bool = True,
            points: int | None = None) -> Path:
    from mvgeo.align import PREVIEW, align_images, write_align_result
    from mvgeo.align.dense_stereo import DenseStereoConfig

    tag = (("" if dense_stereo else ".nostereo") + ("" if downsample == "pixel" else f".{downsample}")
           + ("" if free_space else ".nofreespace") + (f".p{points}" if points else ""))
    out = round_dir.parent / (round_dir.name + ".realign" + tag)
    res = align_images(sorted((round_dir / "denoised").glob("*.png")),
                       dataclasses.replace(PREVIEW, max_focal_log_std=1e9, downsample=downsample,
                                           dense_stereo=DenseStereoConfig(enabled=dense_stereo),
                                           **({} if free_space else {"free_space_rel_tol": 0.0}),
                                           **({"points_budget": points} if points else {})))
    write_align_result(out / "align", res, overwrite=True)
    np.savez(out / "align" / "points.npz", xyz=res.points_xyz, rgb=res.points_rgb, conf=res.points_conf)
    link = out / "denoised"
    if not link.exists():
        link.symlink_to((round_dir / "denoised").resolve())
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("round_dir", type=Path)
    ap.add_argument("data", type=Path)
    ap.add_argument("--iters", type=int, default=300)
    ap.add_argument("--oracle", action="store_true")
    ap.add_argument("--lr-means-x", type=float, default=1.0)
    ap.add_argument("--realign", action="store_true")
    ap.add_argument("--no-dense-stereo", action="store_true", help="with --realign: the alignment's depth maps")
    ap.add_argument("--downsample", choices=["pixel", "voxel"], default="pixel", help="with --realign")
    ap.add_argument("--no-free-space", action="store_true", help="with --realign: without the free-space check")
    ap.add_argument("--mix", choices=["true-cloud", "true-poses"],
                    help="swap in one ground-truth half: the cloud from the true depth (with our cameras) or "
                         "the true cameras (with our cloud)")
    ap.add_argument("--points", type=int, help="with --realign: output point budget (PREVIEW's is 20000)")
    ap.add_argument("--train-images", type=Path,
                    help="train the splat on these images (same names) instead of ROUND/denoised, e.g. the "
                         "noisy inputs with the cameras and cloud of the denoised round")
    ap.add_argument("--no-splat", action="store_true")
    a = ap.parse_args()
    rnd = (realign(a.round_dir, dense_stereo=not a.no_dense_stereo, downsample=a.downsample,
                   free_space=not a.no_free_space, points=a.points) if a.realign else a.round_dir)
    print(json.dumps(depth_check(rnd, a.data)))
    if not a.no_splat:
        print(json.dumps(splat_check(rnd, a.data, a.iters, a.oracle, a.lr_means_x, a.mix, a.train_images)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""How much of each view the alignment's dense cloud covers, with and without hole-filled depth as evidence.

Aligns a folder of photos with a pipeline preset's round-1 alignment settings (`mvgeo.align.align_images`),
twice: as the product does (`covisibility_keep`: a measured point takes evidence for its consistency and
free-space checks from measured depth only, a filled point from every pixel) and with every pixel's depth
as evidence for every point. For each variant and view: the cloud's points that project into the view, and
the cells of an 8 x 8 grid over the view with fewer than 20 of them (a region the splat starts without
Gaussians).

Usage: .venv/bin/python benchmarks/diag_cloud_coverage.py PHOTOS_DIR [--preset fast]

PHOTOS_DIR: e.g. an evaluation's `.../seed0/product/round1/denoised` (the photos the `fast` preset aligns).
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

# isort: off
import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
# isort: on

import mvgeo.align.cloud as cloud  # noqa: E402
from eval.pipeline.config import preset  # noqa: E402
from eval.pipeline.stage_settings import round_settings  # noqa: E402
from mvgeo.align import align_images  # noqa: E402

GRID, MIN_POINTS = 8, 20


def coverage(res) -> dict[str, tuple[int, int]]:
    """view name -> (points projecting into it, grid cells with fewer than MIN_POINTS)."""
    out = {}
    xyz = np.asarray(res.points_xyz, np.float64)
    for n in res.sparse_model.names:
        cam = res.sparse_model.camera_of(n)
        T = np.asarray(res.sparse_model.image(n).cam_from_world, np.float64)[:3]
        x = xyz @ T[:, :3].T + T[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (x @ cam.K.T)[:, :2] / x[:, 2:]
        ok = (x[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        cells = np.zeros((GRID, GRID), int)
        ij = np.clip((uv[ok] / np.array([cam.width, cam.height]) * GRID).astype(int), 0, GRID - 1)
        np.add.at(cells, (ij[:, 1], ij[:, 0]), 1)
        out[n] = (int(ok.sum()), int((cells < MIN_POINTS).sum()))
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("photos", type=Path)
    ap.add_argument("--preset", default="fast")
    args = ap.parse_args()
    cfg = round_settings(preset(args.preset), 1).align.align
    files = sorted(p for p in args.photos.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    product = cloud.covisibility_keep

    def every_pixel_as_evidence(*a, measured=None, **kw):
        return product(*a, **kw)

    results = {}
    for label, fn in (("product (measured points: measured evidence only)", product),
                      ("every pixel as evidence for every point", every_pixel_as_evidence)):
        cloud.covisibility_keep = fn
        t = time.perf_counter()
        res = align_images(files, cfg)
        results[label] = (coverage(res), len(res.points_xyz), time.perf_counter() - t)
    cloud.covisibility_keep = product
    labels = list(results)
    print(f"| view | {' | '.join(f'{lab}: points / empty cells' for lab in labels)} |")
    print(f"|---|{'---|' * len(labels)}")
    for n in results[labels[0]][0]:
        cells = [f"{results[lab][0][n][0]} / {results[lab][0][n][1]}" for lab in labels]
        print(f"| {n} | {' | '.join(cells)} |")
    print(f"| cloud | {' | '.join(f'{results[lab][1]} points, {results[lab][2]:.1f} s' for lab in labels)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Verified pairs and accuracy of `mvgeo align` against its pair-verification settings, on the real sets of
bench_real.py (issue 21, "the match graph at least as dense as COLMAP's exhaustive matching").

Variants: `base` (the defaults: Sampson threshold 1 px at the alignment resolution, at least 20 putative
matches, at least 12 inliers); `m20_i15` (15 inliers, COLMAP's count); `m15_i12` / `m15_i15` (15
putative matches, 12 / 15 inliers); with 20 matches and 15 inliers, `thr1.5` / `thr2` (threshold 1.5 / 2 px);
`thr2_m15` (2 px, 15 matches, 15 inliers); `ratio0.9` (the defaults with Lowe's ratio test at 0.9 instead of
0.8, docs/bench/real_noisy_ring.md).
Sets: data_synth's `object_ring` (a synthetic orbit, its declared noise), DTU scan24 cluster, temple ring and
DTU scan24 spread, each clean and with sigma 25 noise seeds 0..N-1.

Usage: .venv/bin/python benchmarks/diag_match_density.py [VARIANTS] [NOISE_SEEDS]
(e.g. `m20_i15,base 6`; one line per set, noise draw and variant: registered views, verified pairs, bundle-adjustment
tracks, rotation error median / max in degrees, ATE over scene scale, seconds).
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import bench_real as B

from mvgeo.align.api import AlignConfig, align_images
from mvgeo.common.imageio import list_images
from mvgeo.metrics import compare_poses


def variant(threshold_px: float | None, min_matches: int | None = None, min_inliers: int | None = None,
            ratio: float | None = None) -> AlignConfig:
    """`bench_real.OURS` with the pair verification's Sampson threshold, putative-match floor, inlier
    floor and ratio test (None: the defaults'; the inlier floor sets both `TwoViewConfig.min_inliers` and the
    sensitive-SIFT floor)."""
    pw = B.OURS.pairwise
    two_view = pw.two_view
    if threshold_px is not None:
        two_view = replace(two_view, ransac=replace(two_view.ransac, threshold_px=threshold_px))
    if min_matches is not None:
        pw = replace(pw, min_matches=min_matches)
    if ratio is not None:
        pw = replace(pw, ratio=ratio)
    if min_inliers is not None:
        two_view = replace(two_view, min_inliers=min_inliers)
        pw = replace(pw, fallback_min_inliers=min_inliers)
    return replace(B.OURS, pairwise=replace(pw, two_view=two_view))


VARIANTS = {"base": (None, None, None), "m20_i15": (1.0, 20, 15), "m15_i12": (1.0, 15, 12), "m15_i15": (1.0, 15, 15),
            "thr1.5": (1.5, 20, 15), "thr2": (2.0, 20, 15), "thr2_m15": (2.0, 15, 15),
            "ratio0.9": (None, None, None, 0.9)}


def _object_ring(work: Path):
    """data_synth's `object_ring` (12 views, its declared noise): a synthetic orbit, as bench_align renders it."""
    from data_synth import render_scene
    from mvgeo.sparse_model import read_sparse_model

    d = render_scene("object_ring", work / "object_ring", views=12)
    return sorted(list_images(d / "images")), read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()


def _report(label: str, name: str, paths: list[Path], gt: dict) -> None:
    """Align `paths` with variant `name` and print one line: registered, pairs, tracks, errors, seconds."""
    t = time.perf_counter()
    try:
        r = align_images(paths, variant(*VARIANTS[name]))
    except Exception as exc:  # report, keep going
        print(f"{label} {name:9s} failed: {type(exc).__name__}: {str(exc)[:100]} ({time.perf_counter() - t:.1f} s)",
              flush=True)
        return
    sec = time.perf_counter() - t
    m = compare_poses(r.sparse_model.cam_from_world_by_name(), gt)
    ba = r.stats.bundle_adjustment
    rot = f"{m.median_rotation_deg:.3f} / {m.rotation_deg.max():.3f} deg"
    ate = m.ate.rmse / B.scene_scale(gt)
    print(f"{label} {name:9s} registered {m.n_registered:2d}, pairs {r.stats.n_pairs_verified:2d}, "
          f"tracks {ba.n_points if ba else 0:5d}, rot {rot}, ATE/scale {ate:.4f}, {sec:.1f} s", flush=True)


def main() -> None:
    names = sys.argv[1].split(",") if len(sys.argv) > 1 else list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown or not names:
        sys.exit(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    seeds = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    sets = [s for s in (B.dtu_set("cluster"), B.temple_set(), B.dtu_set("spread")) if s is not None]
    work = Path(tempfile.mkdtemp(prefix="match_density_"))
    paths, gt = _object_ring(work)
    for name in names:
        _report(f"{'object_ring (synthetic)':30s}", name, paths, gt)
    if not sets:
        print("no real set found in ../shared/data")
        return
    for s in sets:
        draws = [(False, 0)] + [(True, k) for k in range(seeds)]
        for noisy, seed in draws:
            folder = B.prepare(s, work, noisy, seed)
            paths = [p for p in list_images(folder) if p.name in s.gt]
            for name in names:
                _report(f"{s.name:22s} {f'noisy{seed}' if noisy else 'clean':7s}", name, paths, s.gt)


if __name__ == "__main__":
    main()

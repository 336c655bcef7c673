"""The pair stage of `mvgeo align` on a folder of photos, pair by pair, against a dataset's true cameras.

For every pair of training views: the putative SIFT matches, whether the pair was verified (relative pose
inliers) or why not, and how many of the putative matches the true cameras' epipolar geometry explains
(Sampson distance below 1 px): a pair with many such matches and no verified pose lost evidence in the
pair stage; a pair with few had none to lose. Ends with the connected components of the verified pairs.
The pairs are related with the dataset's calibration (`mvgeo align --intrinsics`).

Usage: .venv/bin/python benchmarks/diag_pair_graph.py DATASET PHOTOS [--all] [--ratio=R]
(DATASET: a folder in the project's layout, `sparse/0` holding the true cameras and `split.json` the training
views; PHOTOS: a folder with those views' photos under their names, e.g. DATASET/images (noisy),
DATASET/clean or an evaluation's round1/denoised; --all: print every pair, not only those with matches;
--ratio: Lowe's ratio of the matching instead of `ClassicalPairConfig.ratio`, to see what a looser test
would admit).
"""
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import cli_option

from mvgeo.align.classical_pairs import ClassicalPairConfig, ClassicalPointmapModel  # imports cv2 first
from mvgeo.align.graph import components
from mvgeo.align.guided import fundamental_from_pose
from mvgeo.align.loops import rotation_angle_deg
from mvgeo.common.imageio import read_image
from mvgeo.epipolar import sampson_distance
from mvgeo.sparse_model import read_sparse_model

dataset, photos = Path(sys.argv[1]), Path(sys.argv[2])
show_all = "--all" in sys.argv
ref = read_sparse_model(dataset / "sparse" / "0")
names = [n for n in json.loads((dataset / "split.json").read_text())["train"] if (photos / n).is_file()]
gt = ref.cam_from_world_by_name()
images = [read_image(photos / n).astype(np.float32) for n in names]
K = np.stack([ref.camera_of(n).K for n in names])
cfg = ClassicalPairConfig()
model = ClassicalPointmapModel(replace(cfg, ratio=float(cli_option("ratio", str(cfg.ratio)))), K_align=K)
pairs = [(i, j) for i in range(len(names)) for j in range(i + 1, len(names))]
ms = model.match(images, pairs)
ps = model.relate(images, ms)
verified = {(g.i, g.j): g for g in ps.geometries}
why = {(f.i, f.j): f.reason for f in ps.failures}
print(f"{photos}: {len(names)} views, keypoints {[len(f.uv_px) for f in ms.features]}, "
      f"sensitive SIFT: {ms.sensitive}")
print("| pair | putative matches | explained by the true cameras | verified inliers | rotation error (deg) | reason |\n"
      "|---|---|---|---|---|---|")
for i, j in pairs:
    m = ms.matches.get((i, j))
    if m is None and not show_all:
        continue
    Ti, Tj = gt[names[i]], gt[names[j]]
    R = Tj[:, :3] @ Ti[:, :3].T
    F = fundamental_from_pose(R, Tj[:, 3] - R @ Ti[:, 3], K[i], K[j])
    n_ok = 0 if m is None else int((sampson_distance(F, *ms.pixels(i, j)) < 1.0).sum())
    g = verified.get((i, j))
    err = "" if g is None else f"{rotation_angle_deg(g.cam_j_from_cam_i[:, :3].T @ R):.1f}"
    print(f"| {Path(names[i]).stem}-{Path(names[j]).stem} | {0 if m is None else len(m)} | {n_ok} | "
          f"{'' if g is None else len(g.matches_px)} | {err} | {why.get((i, j), '')[:80]} |")
comps = components(len(names), list(verified))
print(f"\n{len(verified)} verified pairs; components: "
      + "; ".join("[" + ", ".join(Path(names[k]).stem for k in c) + "]" for c in comps))

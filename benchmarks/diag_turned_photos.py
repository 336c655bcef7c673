"""Photos turned by 90 degrees on a real set: are their cameras, turned back, the photos' own?

Takes a dataset folder (`images/` or `clean/`, `split.json`, `sparse/0` with the true cameras, e.g. the
temple ring made by `denoise-gs dataset import middlebury`), turns two of its training photos into portrait
ones (one clockwise, one counter-clockwise), prepares the working images as `denoise-gs run` does (each
portrait photo turned a quarter counter-clockwise: `eval.pipeline.inputs.prepare_inputs`; the one turned
counter-clockwise comes out upside down), aligns them with `mvgeo align`'s defaults and turns the turned
views' cameras back (`eval.pipeline.publish.turn_back`). Prints each view's rotation error (deg) against its
photo's true camera (the dataset's camera, turned as the photo was), after one best-fit rotation of the world.

Usage: python benchmarks/diag_turned_photos.py DATASET [--photos clean|images]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap)
import numpy as np
from scipy.spatial.transform import Rotation

from eval.pipeline.inputs import reference_working_size
from eval.pipeline.publish import _A_FROM_B_QUARTER, turn_back
from mvgeo.align.api import align_images
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import read_sparse_model


def per_view_rotation_error_deg(est: dict, ref: dict) -> dict[str, float]:
    """Each view's rotation error after the best-fit rotation of the world (chordal mean)."""
    names = [n for n in ref if n in est]
    q = Rotation.from_matrix([np.asarray(est[n])[:3, :3].T @ np.asarray(ref[n])[:3, :3] for n in names]).mean()
    out = {}
    for n in names:
        d = np.asarray(est[n])[:3, :3] @ q.as_matrix() @ np.asarray(ref[n])[:3, :3].T
        out[n] = float(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--photos", choices=("clean", "images"), default="clean")
    args = ap.parse_args()
    train = json.loads((args.dataset / "split.json").read_text())["train"]
    gt = read_sparse_model(args.dataset / "sparse" / "0").cam_from_world_by_name()
    photos = {n: read_image(args.dataset / args.photos / n) for n in train}
    cw, ccw = train[2], train[5]
    photos[cw] = np.ascontiguousarray(np.rot90(photos[cw], k=-1))
    photos[ccw] = np.ascontiguousarray(np.rot90(photos[ccw], k=1))
    truth = dict(gt)  # the photos' own cameras: a photo turned clockwise is turn_back of the original once
    truth[cw] = _A_FROM_B_QUARTER @ np.asarray(gt[cw])[:3]
    truth[ccw] = np.linalg.matrix_power(_A_FROM_B_QUARTER, 3) @ np.asarray(gt[ccw])[:3]
    ref = reference_working_size([(im.shape[1], im.shape[0]) for im in photos.values()])
    turned = {n for n, im in photos.items() if (im.shape[1], im.shape[0]) == ref[::-1]}
    working = [np.ascontiguousarray(np.rot90(im, k=1)) if n in turned else im for n, im in photos.items()]
    res = align_images(working, names=list(photos))
    est = {}
    for im in res.sparse_model.images:
        cam = res.sparse_model.cameras[im.camera_id]
        est[im.name] = turn_back(cam, im.cam_from_world)[1] if im.name in turned else im.cam_from_world
    err = per_view_rotation_error_deg(est, truth)
    print(f"registered {len(est)} of {len(photos)}; turned: {cw} (clockwise), {ccw} (counter-clockwise)")
    print("| view | turned | rotation error (deg) |\n|---|---|---|")
    for n, e in err.items():
        print(f"| {n} | {'yes' if n in turned else ''} | {e:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

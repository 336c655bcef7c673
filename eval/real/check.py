"""Check an imported dataset's ground-truth cameras against its photographs.

Two measurements, independent of any pose estimation:

- **Transfer error.** For each view a and its two nearest views b, c (by
  camera centre), SIFT features matched a-b and a-c (ratio test 0.8, mutual
  best) form tracks seen in all three; each track is triangulated from two of
  the views with the dataset's cameras (linear, in our pixel convention) and
  reprojected into the third. The median distance to the observed feature, in
  pixels, measures the cameras (and the matching noise, about 0.3 px for SIFT)
  together; wrong matches lie in the tail, so the median and the share under
  2 px are reported. A principal-point offset common to every view can be
  tried (`offset_px`): where neighbouring views are rotated against each other
  (Middlebury's 180 degree views) it cannot be absorbed by moving the points,
  so the offset with the lowest median shows the file's pixel convention.
- **Bounding box.** The share of an object's pixels inside the projection
  (convex hull) of a world-space box around the object. Object pixels are
  brighter than `threshold` and coloured (max - min channel above
  `chroma_threshold`): this keeps the tan Middlebury temple and drops its
  black background and grey cloth.

Run: ``python -m eval.real.check DATASET [--offsets -0.5 0 0.5] [--images clean|images]
[--box x0 y0 z0 x1 y1 z1]``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, to_uint
from mvgeo.sparse_model import SparseModel, read_sparse_model

__all__ = ["TransferCheck", "box_coverage", "transfer_error"]


@dataclass(frozen=True)
class TransferCheck:
    """Result of `transfer_error`: `median_px`, `p90_px`, `share_under_2px`, `n_transfers`, `offset_px`."""

    offset_px: float
    median_px: float
    p90_px: float
    share_under_2px: float
    n_transfers: int


def _features(gray: np.ndarray, n: int):
    sift = cv2.SIFT_create(nfeatures=n)
    kp, desc = sift.detectAndCompute(gray, None)
    uv = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2) + 0.5  # OpenCV centres at 0 -> ours
    return uv, desc


def _mutual_matches(d1: np.ndarray, d2: np.ndarray, ratio: float = 0.8) -> dict[int, int]:
    if d1 is None or d2 is None or len(d1) < 2 or len(d2) < 2:
        return {}
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = {m.queryIdx: m.trainIdx for m, n2 in bf.knnMatch(d1, d2, k=2) if m.distance < ratio * n2.distance}
    back = {m.queryIdx: m.trainIdx for m in bf.match(d2, d1)}
    return {i: j for i, j in fwd.items() if back.get(j) == i}


def _triangulate(P1: np.ndarray, P2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(N, 3) linear (DLT) triangulation; P (3, 4) in our pixel convention."""
    A = np.stack([uv1[:, :1] * P1[2] - P1[0], uv1[:, 1:] * P1[2] - P1[1],
                  uv2[:, :1] * P2[2] - P2[0], uv2[:, 1:] * P2[2] - P2[1]], axis=1)
    X = np.linalg.svd(A)[2][:, -1]
    return X[:, :3] / X[:, 3:]


def _projection(model: SparseModel, name: str, offset_px: float) -> np.ndarray:
    K = model.camera_of(name).K.copy()
    K[:2, 2] += offset_px
    return K @ model.image(name).cam_from_world


def transfer_error(dataset: str | Path, *, offsets_px: Sequence[float] = (0.0,), n_features: int = 8000,
                   min_angle_deg: float = 2.0, images: str = "clean") -> list[TransferCheck]:
    """Triplet transfer errors of the dataset's cameras, one per offset (module docstring).

    Args:
        images: the features come from "clean" (`clean/`) or "images" (`images/`, the degraded photos).

    Raises:
        InputError: not a dataset folder, or pinhole-incompatible cameras (distortion).
    """
    root = Path(dataset)
    model = read_sparse_model(root / "sparse" / "0")
    if any(model.cameras[im.camera_id].model not in ("PINHOLE", "SIMPLE_PINHOLE") for im in model.images):
        raise InputError("the transfer check handles pinhole cameras only", path=root / "sparse" / "0")
    if images not in ("clean", "images"):
        raise InputError(f"images must be 'clean' or 'images', got {images!r}")
    names = model.names
    feats = {n: _features(cv2.cvtColor(to_uint(read_image(root / images / n)), cv2.COLOR_RGB2GRAY), n_features)
             for n in names}
    centres = np.array([model.image(n).centre_world for n in names])
    pairs: dict[tuple[int, int], dict[int, int]] = {}
    triplets = []
    for a in range(len(names)):
        b, c = np.argsort(np.linalg.norm(centres - centres[a], axis=1))[1:3]
        for x in (b, c):
            if (a, x) not in pairs:
                pairs[(a, x)] = _mutual_matches(feats[names[a]][1], feats[names[x]][1])
        triplets.append((a, int(b), int(c)))
    out = []
    for off in offsets_px:
        P = {n: _projection(model, n, off) for n in names}
        errs = []
        for a, b, c in triplets:
            common = sorted(set(pairs[(a, b)]) & set(pairs[(a, c)]))
            if not common:
                continue
            uv = {a: feats[names[a]][0][common], b: feats[names[b]][0][[pairs[(a, b)][i] for i in common]],
                  c: feats[names[c]][0][[pairs[(a, c)][i] for i in common]]}
            for i, j, k in ((a, b, c), (a, c, b), (b, c, a)):
                X = _triangulate(P[names[i]], P[names[j]], uv[i], uv[j])
                ci, cj = model.image(names[i]).centre_world, model.image(names[j]).centre_world
                r1, r2 = X - ci, X - cj
                cos = np.sum(r1 * r2, 1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
                x = np.hstack([X, np.ones((len(X), 1))]) @ P[names[k]].T
                ok = (np.degrees(np.arccos(np.clip(cos, -1, 1))) >= min_angle_deg) & (x[:, 2] > 0)
                errs.append(np.linalg.norm(x[ok, :2] / x[ok, 2:] - uv[k][ok], axis=1))
        e = np.concatenate(errs) if errs else np.zeros(0)
        out.append(TransferCheck(float(off), float(np.median(e)) if e.size else float("nan"),
                                 float(np.percentile(e, 90)) if e.size else float("nan"),
                                 float(np.mean(e < 2.0)) if e.size else float("nan"), int(e.size)))
    return out


def box_coverage(dataset: str | Path, box_min_world: Sequence[float], box_max_world: Sequence[float], *,
                 threshold: float = 0.15, chroma_threshold: float = 0.1) -> dict[str, float]:
    """Per view: the share of object pixels (module docstring) inside the projected box's hull."""
    root = Path(dataset)
    model = read_sparse_model(root / "sparse" / "0")
    lo, hi = np.asarray(box_min_world, float), np.asarray(box_max_world, float)
    corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1)
                        for k in (0, 1)])
    out = {}
    for n in model.names:
        img = read_image(root / "clean" / n)
        x = np.hstack([corners, np.ones((8, 1))]) @ _projection(model, n, 0.0).T
        uv = x[:, :2] / x[:, 2:] - 0.5  # ours -> OpenCV pixel centres for the polygon raster
        mask = np.zeros(img.shape[:2], np.uint8)
        cv2.fillConvexPoly(mask, np.round(cv2.convexHull(uv.astype(np.float32))[:, 0] * 16).astype(np.int32), 1,
                           lineType=cv2.LINE_8, shift=4)
        obj = (img.max(axis=2) > threshold) & (img.max(axis=2) - img.min(axis=2) > chroma_threshold)
        out[n] = float((mask.astype(bool) & obj).sum() / max(int(obj.sum()), 1))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m eval.real.check", description=__doc__.split("\n")[0])
    add_common_args(parser)
    parser.add_argument("dataset", type=Path, help="a dataset folder (clean/, sparse/0/)")
    parser.add_argument("--offsets", type=float, nargs="+", default=[0.0],
                        help="principal-point offsets (px) to try, added to every camera")
    parser.add_argument("--images", choices=("clean", "images"), default="clean",
                        help="match features on clean/ (default) or on images/ (the degraded photos)")
    parser.add_argument("--box", type=float, nargs=6, default=None, metavar="X",
                        help="world box x0 y0 z0 x1 y1 z1 around the object: report the object's share inside")

    def run(args: argparse.Namespace) -> int:
        for r in transfer_error(args.dataset, offsets_px=args.offsets, images=args.images):
            print(json.dumps(asdict(r)))
        if args.box is not None:
            cov = box_coverage(args.dataset, args.box[:3], args.box[3:])
            print(json.dumps({"box_coverage_min": min(cov.values()), "box_coverage_median":
                              float(np.median(list(cov.values()))), "per_view": cov}))
        return 0

    return run_cli(run, parser, argv)


if __name__ == "__main__":
    raise SystemExit(main())

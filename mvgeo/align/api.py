"""`align_images`: image files (or arrays) in, poses + intrinsics + dense cloud out; and its writer."""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from mvgeo.align.bundle import BundleConfig, bundle_adjust
from mvgeo.align.classical_pairs import ClassicalPairConfig, ClassicalPointmapModel, pointmap_shape
from mvgeo.align.global_align import GlobalAlignConfig, global_align, pixel_rays
from mvgeo.align.graph import PairGraphSpec, components, make_pairs
from mvgeo.align.intrinsics import undistort_image
from mvgeo.align.pairs import PairFailure, PointmapModel
from mvgeo.align.scene import covisibility_keep, voxel_downsample_by_confidence
from mvgeo.camera import Camera
from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image
from mvgeo.common.timing import StageTimer
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AlignConfig:
    """Options of `align_images` (defaults: the `mvgeo align` CLI's).

    Attributes:
        max_size_px: images are downscaled so that their long side is at most
            this for feature matching; cameras are written at the input size.
        pairs: pair graph (`PairGraphSpec`).
        pairwise: options of the classical pair estimator (incl. the pointmap
            resolution `pointmap_size_px`).
        align: options of the global alignment (`shared_focal` lives there).
        min_conf: output points need a confidence above this (1 = no information).
        points_budget: maximum number of output points (confidence-aware voxel thinning).
        covisibility_rel_tol: relative depth tolerance of the co-visibility pruning.
        bundle_adjust: refine poses and focal(s) by sparse bundle adjustment on
            the pairs' inlier matches after the global alignment (needs a model
            that returns `matches_px`; the classical one does).
        bundle: options of the bundle adjustment.
        seed: RANSAC seed.
    """

    max_size_px: int = 512
    pairs: PairGraphSpec = field(default_factory=PairGraphSpec)
    pairwise: ClassicalPairConfig = field(default_factory=ClassicalPairConfig)
    align: GlobalAlignConfig = field(default_factory=GlobalAlignConfig)
    min_conf: float = 2.0
    points_budget: int = 200_000
    covisibility_rel_tol: float = 0.03
    bundle_adjust: bool = True
    bundle: BundleConfig = field(default_factory=BundleConfig)
    seed: int = 0


#: A faster preset for tests and previews (fewer iterations, smaller pointmaps, at most 20k points).
PREVIEW = AlignConfig(max_size_px=320, pairwise=ClassicalPairConfig(pointmap_size_px=96),
                      align=GlobalAlignConfig(iters=100), points_budget=20_000)


@dataclass
class AlignResult:
    """Output of `align_images`.

    Attributes:
        sparse_model: PINHOLE cameras at the input resolution, `cam_from_world`
            per image (names as given), and the output point cloud.
        points_xyz: (P, 3) float64 world points.
        points_rgb: (P, 3) uint8 colours.
        points_conf: (P,) float32 confidences (>= min_conf).
        stats: JSON-ready report (timings, losses, focals, failed pairs, ...).
    """

    sparse_model: SparseModel
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    points_conf: np.ndarray
    stats: dict


def _load(images: Sequence[Path] | Sequence[np.ndarray], names: Sequence[str] | None
          ) -> tuple[list[np.ndarray], list[str]]:
    if len(images) < 2:
        raise InputError(f"need at least 2 images, got {len(images)}", fix="add more views of the scene")
    if all(isinstance(x, (str, Path)) for x in images):
        paths = [Path(x) for x in images]
        arrays = [read_image(p) for p in paths]
        names = list(names) if names is not None else [p.name for p in paths]
    else:
        arrays = [np.asarray(x, np.float32) for x in images]
        names = list(names) if names is not None else [f"{k:03d}.png" for k in range(len(arrays))]
        paths = [Path(n) for n in names]
    if len(set(names)) != len(names):
        raise InputError("image names are not unique")
    sizes = {a.shape[:2] for a in arrays}
    if len(sizes) > 1:
        listing = ", ".join(f"{n}: {a.shape[1]}x{a.shape[0]}" for n, a in zip(names, arrays, strict=True))
        raise InputError(f"images have different sizes ({listing})",
                         fix="mvgeo align assumes one camera: resize/crop all images to one size first")
    seen: dict[str, str] = {}
    for n, a in zip(names, arrays, strict=True):
        h = hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()
        if h in seen:
            raise InputError(f"images {seen[h]!r} and {n!r} are identical (duplicate views carry no geometry)",
                             path=paths[names.index(n)], fix="remove one of them")
        seen[h] = n
    return arrays, names


def align_images(images: Sequence[Path] | Sequence[np.ndarray], config: AlignConfig = AlignConfig(), *,
                 names: Sequence[str] | None = None, intrinsics: Camera | None = None,
                 model: PointmapModel | None = None) -> AlignResult:
    """Pose-free reconstruction of a few views: pairwise pointmaps + DUSt3R global alignment.

    Args:
        images: image files, or (H, W, 3) float32 RGB arrays in [0, 1], all the same size.
        config: `AlignConfig`.
        names: image names for the output (default: file names, or 000.png, ...).
        intrinsics: known camera (at the input size, any supported model):
            images are undistorted and the focal is fixed instead of estimated.
        model: a `PointmapModel` (default: `ClassicalPointmapModel`).

    Returns:
        `AlignResult`.

    Raises:
        InputError: too few/corrupt/duplicate/mixed-size images, a disconnected
            pair graph (names the images that could not be connected).
        DegenerateGeometryError: the alignment failed numerically.
    """
    timer = StageTimer()
    with timer.stage("load"):
        arrays, names = _load(images, names)
        H0, W0 = arrays[0].shape[:2]
        if intrinsics is not None:
            if (intrinsics.width, intrinsics.height) != (W0, H0):
                raise InputError(f"intrinsics are for {intrinsics.width}x{intrinsics.height} images, "
                                 f"the images are {W0}x{H0}", fix="pass the calibration of these images")
            arrays = [undistort_image(a, intrinsics) for a in arrays]
        s = min(1.0, config.max_size_px / max(H0, W0))
        Ha, Wa = max(1, round(H0 * s)), max(1, round(W0 * s))
        small = [a if (Ha, Wa) == (H0, W0) else cv2.resize(a, (Wa, Ha), interpolation=cv2.INTER_AREA) for a in arrays]
    n = len(arrays)
    K_align = None
    if intrinsics is not None:
        K = intrinsics.K.copy()
        K[0] *= Wa / W0
        K[1] *= Ha / H0
        K_align = np.repeat(K[None], n, axis=0)
    if model is None:
        model = ClassicalPointmapModel(config.pairwise, K_align=K_align, seed=config.seed)
    pairs = make_pairs(n, config.pairs)
    with timer.stage("pairwise"):
        preds, fails = model.predict_pairs(small, pairs)
    _check_connected(n, names, preds, fails)
    Hp, Wp = pointmap_shape(Ha, Wa, model.pointmap_size_px)
    sizes = [(Hp, Wp)] * n
    align_cfg = config.align
    focal_init = None
    if intrinsics is not None:
        # Known calibration: fx at the pointmap grid (square pixels assumed by the alignment).
        focal_init = np.full(n, 0.5 * (intrinsics.fx * Wp / W0 + intrinsics.fy * Hp / H0))
        align_cfg = replace(align_cfg, optimize_focal=False)
    with timer.stage("global_align"):
        res = global_align(preds, sizes, config=align_cfg, focal_init_px=focal_init)
    ba_stats = None
    if config.bundle_adjust:
        matches = [(p.i, p.j, p.matches_px) for p in preds if p.matches_px is not None]
        if matches:
            with timer.stage("bundle_adjust"):
                s_pm = Wa / Wp
                ba_cfg = replace(config.bundle, shared_focal=config.bundle.shared_focal or align_cfg.shared_focal,
                                 optimize_focal=intrinsics is None)
                ba = bundle_adjust(res.cam_from_world, res.focal_px * s_pm, (Wa, Ha), matches, config=ba_cfg)
                res = _reposed(res, ba.cam_from_world, ba.focal_px / s_pm)
                ba_stats = {k: v for k, v in asdict(ba).items() if k not in ("cam_from_world", "focal_px")}
    with timer.stage("scene"):
        K_pm = [np.array([[f, 0, Wp / 2.0], [0, f, Hp / 2.0], [0, 0, 1]]) for f in res.focal_px]
        keep = covisibility_keep(res.pts_world, res.depth, res.conf, res.cam_from_world, K_pm,
                                 rel_depth_tol=config.covisibility_rel_tol)
        xyz, rgb, conf = [], [], []
        for v in range(n):
            col = cv2.resize(arrays[v], (Wp, Hp), interpolation=cv2.INTER_AREA)
            m = keep[v] & (res.conf[v] > config.min_conf)
            xyz.append(res.pts_world[v][m])
            rgb.append(np.clip(np.rint(col[m] * 255), 0, 255).astype(np.uint8))
            conf.append(res.conf[v][m])
        xyz, rgb, conf = np.concatenate(xyz), np.concatenate(rgb), np.concatenate(conf).astype(np.float32)
        sel = voxel_downsample_by_confidence(xyz, conf, config.points_budget)
        xyz, rgb, conf = xyz[sel], rgb[sel], conf[sel]
    cameras, posed = {}, []
    for v in range(n):
        if intrinsics is not None:
            cam = Camera.pinhole(intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, W0, H0)
        else:
            f = float(res.focal_px[v])
            cam = Camera.pinhole(f * W0 / Wp, f * H0 / Hp, W0 / 2.0, H0 / 2.0, W0, H0)
        cameras[v + 1] = cam
        posed.append(PosedImage(names[v], v + 1, res.cam_from_world[v]))
    sparse = SparseModel(cameras, posed, xyz, rgb)
    stats = {
        "n_images": n,
        "input_size_wh": [W0, H0],
        "align_size_wh": [Wa, Ha],
        "pointmap_size_wh": [Wp, Hp],
        "n_pairs": len(pairs),
        "n_pairs_ok": len(preds),
        "failed_pairs": [{"i": names[f.i], "j": names[f.j], "reason": f.reason} for f in fails],
        "iterations": align_cfg.iters,
        "init_loss": res.init_loss,
        "final_loss": res.final_loss,
        "focal_px": {names[v]: cameras[v + 1].fx for v in range(n)},
        "known_intrinsics": intrinsics is not None,
        "shared_focal": align_cfg.shared_focal,
        "bundle_adjustment": ba_stats,
        "n_points": int(len(xyz)),
        "mean_confidence": float(conf.mean()) if len(conf) else float("nan"),
        "timings_s": timer.as_dict(),
        "config": _jsonable(asdict(config)),
    }
    return AlignResult(sparse, xyz, rgb, conf, stats)


def _reposed(res, cam_from_world: np.ndarray, focal_px: np.ndarray):
    """The alignment result with new poses/focals; dense points re-projected from the depth maps."""
    pts = []
    for v, d in enumerate(res.depth):
        H, W = d.shape
        R, t = cam_from_world[v][:, :3], cam_from_world[v][:, 3]
        pts.append(((pixel_rays(H, W, float(focal_px[v])) * d[..., None]) - t) @ R)
    return replace(res, cam_from_world=cam_from_world, focal_px=np.asarray(focal_px, float), pts_world=pts)


def _check_connected(n: int, names: list[str], preds, fails: list[PairFailure]) -> None:
    comps = components(n, [(p.i, p.j) for p in preds])
    if len(comps) == 1:
        return
    main = comps[0]
    lost = [names[v] for c in comps[1:] for v in c]
    reasons = "; ".join(f"({names[f.i]}, {names[f.j]}): {f.reason}" for f in fails
                        if (f.i in main) != (f.j in main))[:2000]
    raise InputError(
        f"the pair graph is disconnected: images {lost} could not be related to {[names[v] for v in main]}"
        + (f". Failed pairs: {reasons}" if reasons else ""),
        fix="add views that overlap the disconnected ones, or remove them; try --pairs complete")


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (bool, int, float, str)) or x is None:
        return x
    return str(x)


def write_align_result(out: str | Path, result: AlignResult) -> Path:
    """Write `OUT/sparse/0/*.bin`, `OUT/points.ply` and `OUT/align.json` atomically.

    Returns:
        `out`.
    """
    out = Path(out)
    with atomic_output_dir(out) as tmp:
        write_sparse_model(tmp / "sparse" / "0", result.sparse_model, binary=True)
        write_points_ply(tmp / "points.ply", result.points_xyz, result.points_rgb, result.points_conf)
        (tmp / "align.json").write_text(json.dumps(result.stats, indent=2, allow_nan=True))
    return out


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, conf: np.ndarray) -> None:
    """Binary PLY: x y z float32, red green blue uint8, confidence float32 (Open3D reads it)."""
    from plyfile import PlyData, PlyElement

    arr = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1"), ("confidence", "f4")])
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    arr["red"], arr["green"], arr["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    arr["confidence"] = conf
    PlyData([PlyElement.describe(arr, "vertex")], text=False).write(str(path))


__all__ = ["AlignConfig", "AlignResult", "PREVIEW", "align_images", "write_align_result"]

"""Load a training folder (`images/`, `sparse/0/`, optional `split.json`, `depth/`) and initial points.

The folder layout is docs/conventions.md's dataset folder (written by
`data_synth`, or `mvgeo align` output plus its images).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData

from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image
from mvgeo.common.jsonio import read_json_object
from mvgeo.common.npyio import load_numpy
from mvgeo.sparse_model import SparseModel, read_sparse_model


@dataclass
class TrainingViews:
    """Posed images of one split.

    Attributes:
        names: image file names (relative to `images/`).
        images: HxWx3 float32 RGB in [0, 1].
        cameras: one `Camera` per image.
        cam_from_world: (N, 3, 4) float64.
        sparse: the whole sparse model (all images, points).
    """

    names: list[str]
    images: list[np.ndarray]
    cameras: list[Camera]
    cam_from_world: np.ndarray
    sparse: SparseModel


def _sparse_dir(data_dir: Path) -> Path:
    for cand in (data_dir / "sparse" / "0", data_dir / "sparse"):
        if (cand / "cameras.txt").exists() or (cand / "cameras.bin").exists():
            return cand
    raise InputError("no COLMAP model found (looked for sparse/0/ and sparse/)", path=data_dir,
                     fix="DATA_DIR must hold images/ and sparse/0/ (a data-synth render or mvgeo align output)")


#: What `split.json` holds, quoted in the errors about it.
SPLIT_FORMAT = 'split.json must be UTF-8 JSON {"train": ["NAME.png", ...], "test": ["NAME.png", ...]}'


def read_split(data_dir: Path, split: str) -> list[str] | None:
    """Names in `split.json[split]`, or None when the folder has no split file.

    Raises:
        InputError: the file cannot be read or decoded, is not JSON, or `split` is not a list of names.
    """
    path = data_dir / "split.json"
    if not path.exists():
        return None
    data = read_json_object(path, fix=SPLIT_FORMAT)
    if split not in data:
        raise InputError(f"split.json has no '{split}' list", path=path, fix=SPLIT_FORMAT)
    names = data[split]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError(f"split.json's '{split}' must be a list of image names (strings), got {names!r:.80}",
                         path=path, fix=SPLIT_FORMAT)
    return names


def load_views(data_dir: str | Path, *, split: str | None = "train", sparse_dir: str | Path | None = None
               ) -> TrainingViews:
    """Images and cameras of `data_dir`, restricted to `split` when `split.json` exists.

    Raises:
        InputError: missing folders/files, images without poses or poses without images,
            image sizes that differ from their camera.
    """
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise InputError("data folder not found", path=data_dir,
                         fix="give a folder with images/ and sparse/0/ (as `denoise-gs dataset import` or "
                             "`mvgeo align --out` write it)")
    image_dir = data_dir / "images"
    if not image_dir.is_dir():
        raise InputError("no images/ folder", path=data_dir, fix="DATA_DIR must hold images/ and sparse/0/")
    sparse = read_sparse_model(Path(sparse_dir) if sparse_dir else _sparse_dir(data_dir))
    names = sparse.names
    wanted = read_split(data_dir, split) if split else None
    if wanted is not None:
        unknown = sorted(set(wanted) - set(names))
        if unknown:
            raise InputError(f"split '{split}' names images with no camera pose: {unknown[:5]}",
                             path=data_dir / "split.json",
                             fix="name only images that sparse/0 has a camera for (their file names)")
        names = [n for n in names if n in set(wanted)]
        if not names:
            raise InputError(f"split.json's '{split}' list is empty: no images to use", path=data_dir / "split.json",
                             fix=f"list the images of the '{split}' views, or leave split.json out to use them all")
    if not names:
        raise InputError("no posed images to use: sparse/0 has no image", path=data_dir,
                         fix="point at a model with registered images (e.g. what `mvgeo align --out` writes)")
    images, cameras = [], []
    for name in names:
        path = image_dir / name
        if not path.exists():
            raise InputError(f"image {name!r} is in the COLMAP model but not in images/", path=path,
                             fix="put the image back, or give the model that was made from these images")
        img = read_image(path)
        cam = sparse.camera_of(name)
        if img.shape[:2] != (cam.height, cam.width):
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but its camera is {cam.width}x{cam.height}",
                             path=path, fix="resize the images or the cameras consistently")
        images.append(img)
        cameras.append(cam)
    poses = np.stack([sparse.image(n).cam_from_world for n in names])
    return TrainingViews(names=names, images=images, cameras=cameras, cam_from_world=poses, sparse=sparse)


def read_point_cloud_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """xyz (P, 3) float64 and rgb (P, 3) uint8 from a point-cloud PLY (grey when it has no colour)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("initial point cloud not found", path=path,
                         fix="give the points.ply `mvgeo align` writes, or --init depth")
    try:
        v = PlyData.read(str(path))["vertex"]
        xyz = np.stack([np.asarray(v[k], dtype=np.float64) for k in ("x", "y", "z")], 1)
    except Exception as exc:  # plyfile raises several types on corrupt input
        raise InputError(f"cannot read a point cloud from this PLY ({exc})", path=path,
                         fix="give a PLY of 3D points with x, y, z (e.g. `mvgeo align`'s)") from exc
    names = [p.name for p in v.properties]
    if all(k in names for k in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(v[k]) for k in ("red", "green", "blue")], 1)
        rgb = rgb.astype(np.uint8) if rgb.dtype == np.uint8 else np.clip(rgb * 255.0, 0, 255).astype(np.uint8)
    else:
        rgb = np.full((len(xyz), 3), 128, np.uint8)
    return xyz, rgb


def points_from_depth(data_dir: str | Path, views: TrainingViews, *, stride_px: int = 4
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Back-project every `stride_px`-th pixel of each view's `depth/NAME.npy` (z-depth, inf = miss).

    Uses the ground-truth depth a `data_synth` folder ships: an oracle initialisation for
    benchmarks with known geometry (the real pipeline initialises from `mvgeo align`).

    Raises:
        InputError: a view has no depth map, or one that is unreadable or not one value per pixel.
    """
    depth_dir = Path(data_dir) / "depth"
    xyz_all, rgb_all = [], []
    for name, img, cam, pose in zip(views.names, views.images, views.cameras, views.cam_from_world, strict=True):
        path = depth_dir / (Path(name).stem + ".npy")
        if not path.exists():
            raise InputError("no depth map for this view", path=path,
                             fix="use --init POINTS.ply or a sparse model with points")
        depth = load_numpy(path, fix="write it with numpy.save as an (H, W) float array, or use --init POINTS.ply")
        if not isinstance(depth, np.ndarray) or depth.shape != (cam.height, cam.width):
            raise InputError(f"depth map has shape {getattr(depth, 'shape', None)}, its view is "
                             f"{cam.width}x{cam.height} (expected ({cam.height}, {cam.width}))", path=path,
                             fix="write one (H, W) depth value per pixel of the view, or use --init POINTS.ply")
        rows, cols = np.mgrid[0:cam.height:stride_px, 0:cam.width:stride_px]
        z = depth[rows, cols]
        ok = np.isfinite(z) & (z > 0)
        u, v, z = cols[ok] + 0.5, rows[ok] + 0.5, z[ok]
        x_cam = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
        R, t = pose[:, :3], pose[:, 3]
        xyz_all.append((x_cam - t) @ R)
        rgb_all.append(np.clip(img[rows[ok], cols[ok]] * 255.0 + 0.5, 0, 255).astype(np.uint8))
    return np.concatenate(xyz_all), np.concatenate(rgb_all)

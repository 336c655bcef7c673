"""Pose-based grouping of views and choice of the sharpest view per group (round 2).

Each view gets a 6-D feature: its camera centre, centred on the mean centre
and divided by the scene scale (the RMS distance of the centres from their
mean), followed by its unit forward (viewing) axis in world coordinates
(docs/conventions.md: ``C = -R^T t``, forward = ``R^T [0, 0, 1]``). Both
halves have comparable spread (about 1), so position and direction count
alike. The features are clustered with k-means (k-means++ seeding, seeded
restarts, `denoise.kmeans`), and in each cluster the view whose grayscale
image has the largest variance of the Laplacian (the usual focus / blur
measure, `cv2.Laplacian`) is selected.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from denoise.kmeans import kmeans
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError, ShapeError
from mvgeo.common.imageio import read_image


@dataclass(frozen=True)
class Selection:
    """The views chosen for round 2 and why.

    Attributes:
        names: selected view names, in input order.
        cluster_of: view name -> cluster index (``0..k-1``).
        laplacian_var: view name -> variance of the Laplacian of its grayscale image ([0, 1] units).
        features: view name -> its 6-D feature (normalised centre, forward axis).
        k: number of clusters actually used (``min(k, N)``).
        inertia: k-means objective of the chosen clustering.
        scene_scale: the RMS distance of camera centres from their mean (world units).
    """

    names: list[str]
    cluster_of: dict[str, int]
    laplacian_var: dict[str, float]
    features: dict[str, list[float]]
    k: int
    inertia: float
    scene_scale: float

    def to_json_dict(self) -> dict:
        """A JSON-serialisable dict (what `denoise select` writes)."""
        return {
            "selected": list(self.names),
            "k": self.k,
            "inertia": self.inertia,
            "scene_scale": self.scene_scale,
            "views": {
                n: {"cluster": self.cluster_of[n], "laplacian_var": self.laplacian_var[n],
                    "feature": self.features[n], "selected": n in self.names}
                for n in self.cluster_of
            },
        }


def pose_features(cam_from_world: np.ndarray) -> tuple[np.ndarray, float]:
    """6-D features of cameras.

    Args:
        cam_from_world: ``(N, 3, 4)`` or ``(N, 4, 4)`` float64.

    Returns:
        ``(features (N, 6), scene_scale)``; with all centres equal (pure
        rotation) the scale is 0 and the centre half of the features is 0.
    """
    m = np.asarray(cam_from_world, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] not in ((3, 4), (4, 4)):
        raise ShapeError(f"cam_from_world: expected (N, 3, 4) or (N, 4, 4), got {m.shape}")
    if not np.isfinite(m[:, :3]).all():
        raise InputError("cam_from_world contains NaN or inf")
    R, t = m[:, :3, :3], m[:, :3, 3]
    centres = -np.einsum("nji,nj->ni", R, t)  # -R^T t
    forward = R[:, 2, :]  # R^T [0, 0, 1] = third row of R
    forward = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    rel = centres - centres.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum(rel**2, axis=1))))
    # Relative tolerance: centres equal up to rounding count as one position.
    if scale <= 1e-12 * max(1.0, float(np.abs(centres).max())):
        scale = 0.0
        rel_n = np.zeros_like(rel)
    else:
        rel_n = rel / scale
    return np.concatenate([rel_n, forward], axis=1), scale


def laplacian_variance(img: np.ndarray) -> float:
    """Variance of the 3x3 Laplacian of the grayscale image (float32 [0, 1] units; higher = sharper).

    Args:
        img: ``(H, W, 3)`` RGB or ``(H, W)`` gray float in [0, 1].
    """
    a = np.asarray(img, dtype=np.float32)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.shape[2] == 3 else a[:, :, 0]
    if a.ndim != 2:
        raise ShapeError(f"image: expected (H, W) or (H, W, 3), got {np.asarray(img).shape}")
    return float(cv2.Laplacian(a, cv2.CV_32F, ksize=1).var())


def select_views(cam_from_world: Mapping[str, np.ndarray] | np.ndarray,
                 images: Mapping[str, np.ndarray | str | Path] | Sequence[np.ndarray | str | Path],
                 k: int = 12, *, names: Sequence[str] | None = None, seed: int = 0,
                 restarts: int = 8) -> Selection:
    """Group views by pose and keep the sharpest of each group.

    Args:
        cam_from_world: view name -> ``(3, 4)``/``(4, 4)`` world-to-camera matrix, or an
            ``(N, 3, 4)``/``(N, 4, 4)`` array together with `names`.
        images: view name -> image array (``(H, W, 3)`` float [0, 1]) or image file path, or a
            sequence in the order of `names`.
        k: number of views to keep (round-2 views, default 12); ``k >= N`` keeps every view.
        names: view names when `cam_from_world` is an array (default ``"0", "1", ...``).
        seed: seeds the k-means restarts.
        restarts: k-means++ restarts (the lowest-inertia clustering wins).

    Returns:
        `Selection`.

    Raises:
        InputError: no views, an image missing for a view, unreadable image files.
    """
    if isinstance(cam_from_world, Mapping):
        view_names = list(cam_from_world)
        poses = np.stack([np.asarray(cam_from_world[n], dtype=np.float64)[:3] for n in view_names]) \
            if view_names else np.zeros((0, 3, 4))
    else:
        poses = np.asarray(cam_from_world, dtype=np.float64)
        view_names = list(names) if names is not None else [str(i) for i in range(len(poses))]
        if len(view_names) != len(poses):
            raise ShapeError(f"{len(view_names)} names for {len(poses)} poses")
    if len(view_names) == 0:
        raise InputError("no views to select from", fix="pass at least one posed view")
    if k < 1:
        raise InputError(f"k must be >= 1, got {k}")
    if isinstance(images, Mapping):
        missing = [n for n in view_names if n not in images]
        if missing:
            raise InputError(f"no image for view(s) {missing[:5]}", fix="give an image for every posed view")
        imgs = [images[n] for n in view_names]
    else:
        imgs = list(images)
        if len(imgs) != len(view_names):
            raise InputError(f"{len(imgs)} images for {len(view_names)} poses")
    feats, scale = pose_features(poses)
    lap = {}
    for n, im in zip(view_names, imgs, strict=True):
        arr = read_image(im) if isinstance(im, str | Path) else im
        lap[n] = laplacian_variance(arr)
    k_used = min(k, len(view_names))
    res = kmeans(feats, k_used, seed=seed, restarts=restarts)
    chosen = set()
    for j in range(k_used):
        members = [n for n, lab in zip(view_names, res.labels, strict=True) if lab == j]
        chosen.add(max(members, key=lambda n: lap[n]))  # ties: the first in input order
    return Selection(
        names=[n for n in view_names if n in chosen],
        cluster_of={n: int(lab) for n, lab in zip(view_names, res.labels, strict=True)},
        laplacian_var=lap,
        features={n: [float(v) for v in f] for n, f in zip(view_names, feats, strict=True)},
        k=k_used,
        inertia=res.inertia,
        scene_scale=scale,
    )

"""Initialisation of the global alignment from the pairs' own relative poses.

DUSt3R's initialisation (`init_from_spanning_tree`) chains the pairs' *pointmaps*
with Procrustes and then poses each view by PnP on its chained points. With
narrow fields of view and weak pairs (few confident pixels, small depth
relief) the Procrustes rotation of two differently distorted pointmaps of
the same view can be tens of degrees off the pair's own relative rotation,
and the errors compound along the tree (measured on temple_sparse_ring:
views 50-180 deg off after the initialisation, a local minimum the bundle
adjustment did not leave).

Here each tree pair contributes the relative pose its pointmap implies (PnP of
view j's points, which live in camera i's frame, against j's pixel grid), and
only the *scale* comes from the pointmaps: the median ratio of the shared
view's depths in the world and in the new pair. Poses chain along the same
maximum spanning tree (Prim's order from the strongest pair).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvgeo.align.pairs import PairPrediction
from mvgeo.align.pointmap_geometry import PNP_REFINE_POINTS, AlignInit
from mvgeo.common.deps import cv2
from mvgeo.common.errors import UnposedViewsError
from mvgeo.pnp import sqpnp


def _valid(C: np.ndarray, P: np.ndarray) -> np.ndarray:
    return (C > 1.0) & np.all(np.isfinite(P), axis=-1) & (P[..., 2] > 0)


def pair_pose_from_pointmap(p: PairPrediction, focal_j_px: float) -> tuple[np.ndarray, np.ndarray] | None:
    """cam_j_from_cam_i (R, t) in the pair's units: PnP of `pts_j` on view j's pixel grid; None if it fails."""
    H, W = p.conf_j.shape
    ok = _valid(p.conf_j, p.pts_j)
    rows, cols = np.nonzero(ok)
    if len(rows) < 6:
        return None
    uv = np.stack([cols, rows], axis=1).astype(np.float64)  # OpenCV pixel centres at integers
    K = np.array([[focal_j_px, 0, W / 2.0 - 0.5], [0, focal_j_px, H / 2.0 - 0.5], [0, 0, 1]])
    obj = p.pts_j[ok].astype(np.float64)
    okp, rvec, tvec = sqpnp(obj, uv, K)
    if not okp:
        return None
    sub = np.linspace(0, len(obj) - 1, min(len(obj), PNP_REFINE_POINTS)).round().astype(int)
    rvec, tvec = cv2.solvePnPRefineLM(obj[sub], uv[sub], K, None, rvec, tvec)
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3)


def init_from_pair_poses(preds: Sequence[PairPrediction], sizes_hw: Sequence[tuple[int, int]], *,
                         focal_init_px: np.ndarray,
                         rel_override: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] | None = None
                         ) -> AlignInit:
    """Chain the tree pairs' relative poses (module docstring); depths and pair similarities as DUSt3R's init.

    Args:
        rel_override: (i, j) -> (R, unit t) cam_j_from_cam_i to use instead of the
            pointmap's rotation and translation direction (e.g. from the pair's
            matches at a better focal); the pointmap still gives the baseline length.

    Raises:
        DegenerateGeometryError: a view could not be reached by any usable pair.
    """
    n = len(sizes_hw)
    scores = [max(p.score, 1e-6) for p in preds]
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # view -> (R cam_from_world, centre)
    depth: dict[int, np.ndarray] = {}
    conf: dict[int, np.ndarray] = {}
    rel: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}

    def own_depths(k: int, p: PairPrediction):
        R, t = rel[k]
        zi = p.pts_i[..., 2].astype(np.float64)
        zj = (p.pts_j.astype(np.float64) @ R.T + t)[..., 2]
        return zi, zj

    bad: set[int] = set()
    while len(poses) < n:
        if not poses:
            order = sorted(range(len(preds)), key=lambda k: -scores[k])
        else:
            order = sorted((k for k, p in enumerate(preds) if k not in bad and ((p.i in poses) != (p.j in poses))),
                           key=lambda k: -scores[k])
        if not order:
            break
        for k in order:
            if k in bad:
                continue
            p = preds[k]
            if k not in rel:
                rel[k] = pair_pose_from_pointmap(p, float(focal_init_px[p.j]))
            if rel[k] is None:
                bad.add(k)
                continue
            zi, zj = own_depths(k, p)
            R_ji, t_ji = rel[k]  # cam_j_from_cam_i
            if rel_override and (p.i, p.j) in rel_override:
                R_o, t_o = rel_override[(p.i, p.j)]
                R_ji, t_ji = R_o, t_o / max(np.linalg.norm(t_o), 1e-12) * np.linalg.norm(t_ji)
            if not poses:  # the strongest pair fixes the world (camera i) and the scale
                s = 1.0
                poses[p.i] = (np.eye(3), np.zeros(3))
            else:
                known, z_pair = (p.i, zi) if p.i in poses else (p.j, zj)
                ok = (conf[known] > 1.0) & (z_pair > 0) & _valid(p.conf_i if known == p.i else p.conf_j,
                                                                  p.pts_i if known == p.i else p.pts_j)
                if np.count_nonzero(ok) < 3:
                    bad.add(k)
                    continue
                s = float(np.median(depth[known][ok] / z_pair[ok]))
                if not s > 0:
                    bad.add(k)
                    continue
            if p.i in poses and p.j not in poses:
                R_i, c_i = poses[p.i]
                R_j = R_ji @ R_i
                c_j = c_i + s * R_i.T @ (-R_ji.T @ t_ji)
                poses[p.j] = (R_j, c_j)
            elif p.j in poses and p.i not in poses:
                R_j, c_j = poses[p.j]
                R_i = R_ji.T @ R_j
                c_i = c_j + s * R_j.T @ t_ji
                poses[p.i] = (R_i, c_i)
            for v, z, C in ((p.i, zi, p.conf_i), (p.j, zj, p.conf_j)):
                if v not in depth:
                    depth[v], conf[v] = s * z, C
            break
        else:
            break
    missing = [v for v in range(n) if v not in poses]
    if missing:
        raise UnposedViewsError("not reached by any pair with a usable relative pose", views=missing)
    cam_from_world = np.zeros((n, 3, 4))
    depth_list = []
    for v in range(n):
        R, c = poses[v]
        cam_from_world[v] = np.concatenate([R, (-R @ c).reshape(3, 1)], axis=1)
        z = depth[v]
        ok = (conf[v] > 1.0) & (z > 0) & np.isfinite(z)
        med = float(np.median(z[ok])) if np.any(ok) else float("nan")
        if not med > 0:
            raise UnposedViewsError("no confident pixel with positive depth", views=[v])
        depth_list.append(np.where(ok & (z > 1e-3 * med), z, med))
    return AlignInit(cam_from_world, np.asarray(focal_init_px, np.float64).copy(), depth_list)

"""Triangulation with validity (numpy float64): DLT, midpoint, Lee–Civera mid2, multi-view.

Every result is a `Triangulation` carrying per-point validity (cheirality,
triangulation angle, range, reprojection error). Points that cannot be
triangulated (parallel or divergent rays, points at infinity) are flagged and
hold a *finite* placeholder (the point along the first ray at
``TriangulationCriteria.max_range``), never NaN/Inf.

Frames: two-view functions work in camera 1's frame: ``rays1`` in camera 1,
``rays2`` in camera 2, and ``cam2_from_cam1 = [R | t]`` (docs/conventions.md).
Rays need not be unit length (``[x, y, 1]`` from `Camera.unproject` is fine).
Multi-view functions take world-frame poses ``cam_from_world``.

Methods (Lee & Civera, "Triangulation: Why Optimize?", BMVC 2019):
- ``"midpoint"``: midpoint of the common perpendicular (minimises 3-D distance to the rays).
- ``"mid2"``: Lee–Civera's alternative midpoint, depths from the sine rule
  ``l1 = |f2 x b| / |f1 x f2|``, ``l2 = |f1 x b| / |f1 x f2|`` then the midpoint
  of ``l1 f1`` and ``b + l2 f2`` (unit rays ``f``, baseline ``b`` = camera 2's
  centre). Better 2-D and 3-D accuracy than the midpoint at the same cost;
  mrcal recommends it.
- ``"dlt"``: linear homogeneous least squares on the normalised image points
  (Hartley–Zisserman 12.2), via SVD; handles points at infinity gracefully
  (w -> 0), then flagged by the angle test.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from mvgeo.common.errors import DegenerateGeometryError, ShapeError, check_shape
from mvgeo.transforms import Rt_from_matrix

__all__ = [
    "TriangulationCriteria",
    "Triangulation",
    "triangulate_two_view",
    "triangulate_multiview",
    "triangulate_views_px",
]

Method = Literal["mid2", "midpoint", "dlt"]


@dataclass(frozen=True)
class TriangulationCriteria:
    """Thresholds deciding `Triangulation.valid`.

    Attributes:
        min_angle_deg: minimum triangulation angle (largest angle between the
            viewing rays, degrees). 1.5 is COLMAP's mapper default; below it
            depth is poorly determined (depth error ~ pixel noise / angle).
        max_angular_error_deg: maximum angle between an observed ray and the
            direction to the triangulated point, over views (degrees). 0.5 deg
            is ~4 px at 500 px focal, COLMAP's 4 px reprojection filter.
        max_range: points farther than this (in units of the *largest baseline*)
            from the first camera are treated as at infinity.
        max_reprojection_error_px: for the pixel-level `triangulate_views_px` only.
    """

    min_angle_deg: float = 1.5
    max_angular_error_deg: float = 0.5
    max_range: float = 1e4
    max_reprojection_error_px: float = 4.0


DEFAULT_CRITERIA = TriangulationCriteria()


@dataclass(frozen=True)
class Triangulation:
    """Triangulated points and why each one can or cannot be trusted.

    Attributes:
        points: (N, 3) float64, finite; in camera 1's frame (two-view) or the world frame (multi-view).
        valid: (N,) bool: all of the checks below pass.
        in_front: (N,) bool: positive depth in every observing camera (cheirality).
        angle_deg: (N,) largest angle between observing rays at the point.
        range: (N,) distance from the first camera centre, in the scene's units.
        angular_error_deg: (N,) largest angle between an observed ray and the point's direction.
        finite: (N,) bool: the rays were not parallel/divergent, so a point
            exists; False points hold the placeholder described in the module docs.
        reprojection_error_px: (N,) largest reprojection error over views, or
            None when no cameras were given.
    """

    points: np.ndarray
    valid: np.ndarray
    in_front: np.ndarray
    angle_deg: np.ndarray
    range: np.ndarray
    angular_error_deg: np.ndarray
    finite: np.ndarray
    reprojection_error_px: np.ndarray | None = None


def _unit(v: np.ndarray) -> np.ndarray:
    # (N, 3) rows: `_rownorm` (same value; np.linalg.norm reduces over the 3-long axis slowly).
    n = _rownorm(v)[:, None] if v.ndim == 2 and v.shape[1] == 3 else np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in radians between vectors (..., 3), accurate at 0 and pi (atan2 form)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def _check_rays(rays, name: str) -> np.ndarray:
    r = np.asarray(rays, dtype=np.float64)
    check_shape(r, ["N", 3], name)
    return r


def _finalise(points, finite, centres, rays_world, criteria, cam_R, cam_t):
    """Common validity computation. centres (V, 3); rays_world (V, N, 3); cam_R (V, 3, 3), cam_t (V, 3)."""
    baseline = max(float(np.max(np.linalg.norm(centres - centres[0], axis=-1))), 1e-300)
    max_range = criteria.max_range * baseline
    f1 = _unit(rays_world[0])
    finite = finite & np.all(np.isfinite(points), axis=-1)
    points = np.where(finite[:, None], points, centres[0] + max_range * f1)
    rng = np.linalg.norm(points - centres[0], axis=-1)
    far = rng > max_range
    points = np.where(far[:, None], centres[0] + max_range * _unit(points - centres[0]), points)
    rng = np.minimum(rng, max_range)
    # Depth in each camera (cheirality) and angles.
    depth = np.einsum("vij,nj->vni", cam_R, points)[..., 2] + cam_t[:, None, 2]
    observed = np.any(rays_world != 0, axis=-1)  # (V, N)
    in_front = np.all((depth > 0) | ~observed, axis=0)
    to_point = points[None] - centres[:, None]  # (V, N, 3)
    ang_err = np.where(observed, _angle_between(to_point, rays_world), 0.0).max(axis=0)
    # Triangulation angle: largest pairwise angle between observing rays (at the point).
    V = centres.shape[0]
    tri = np.zeros(points.shape[0])
    for a in range(V):
        for b in range(a + 1, V):
            both = observed[a] & observed[b]
            ang = _angle_between(points - centres[a], points - centres[b])
            tri = np.where(both, np.maximum(tri, ang), tri)
    angle_deg = np.degrees(tri)
    ang_err_deg = np.degrees(ang_err)
    valid = (
        finite
        & ~far
        & in_front
        & (angle_deg >= criteria.min_angle_deg)
        & (ang_err_deg <= criteria.max_angular_error_deg)
    )
    return Triangulation(
        points=points,
        valid=valid,
        in_front=in_front,
        angle_deg=angle_deg,
        range=rng,
        angular_error_deg=ang_err_deg,
        finite=finite,
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross's products, without its axis handling)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _rownorm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm of each row of (N, 3) (same summation order as np.linalg.norm(axis=-1))."""
    return np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])


def _any_row(a: np.ndarray) -> np.ndarray:
    """`(a != 0).any(axis=-1)` for (N, 3) rows (column by column: reductions over a 3-long axis are slow)."""
    return (a[:, 0] != 0) | (a[:, 1] != 0) | (a[:, 2] != 0)


def _finite_rows(a: np.ndarray) -> np.ndarray:
    """`np.isfinite(a).all(axis=-1)` for (N, 3) rows."""
    return np.isfinite(a[:, 0]) & np.isfinite(a[:, 1]) & np.isfinite(a[:, 2])


def _rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _angle_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`_angle_between` for (N, 3) rows."""
    return np.arctan2(_rownorm(_cross(a, b)), _rowdot(a, b))


def _finalise_two_view(points, finite, c2, r1, r2w, criteria, R, t) -> Triangulation:
    """`_finalise` for two cameras (camera 1 at the origin), without the V-generic einsums.

    The hot path of `triangulate_two_view` (RANSAC cheirality and the dense pointmaps call it
    hundreds of times on 10^3-10^4 rays). ``r2w``: camera 2's rays in camera 1's frame.
    `_finalise` is the reference it is tested against.
    """
    baseline = max(float(np.linalg.norm(c2)), 1e-300)
    max_range = criteria.max_range * baseline
    finite = finite & _finite_rows(points)
    if not finite.all():
        n1 = _rownorm(r1)[:, None]
        points = np.where(finite[:, None], points, max_range * (r1 / np.where(n1 > 0, n1, 1.0)))
    rng = _rownorm(points)
    far = rng > max_range
    if far.any():
        n = rng[:, None]
        points = np.where(far[:, None], max_range * (points / np.where(n > 0, n, 1.0)), points)
        rng = np.minimum(rng, max_range)
    obs1 = _any_row(r1)
    obs2 = _any_row(r2w)
    depth2 = points @ R[2] + t[2]
    in_front = ((points[:, 2] > 0) | ~obs1) & ((depth2 > 0) | ~obs2)
    to2 = points - c2
    err1 = np.where(obs1, _angle_rows(points, r1), 0.0)
    err2 = np.where(obs2, _angle_rows(to2, r2w), 0.0)
    ang_err_deg = np.degrees(np.maximum(err1, err2))
    angle_deg = np.degrees(np.where(obs1 & obs2, np.maximum(0.0, _angle_rows(points, to2)), 0.0))
    valid = (finite & ~far & in_front & (angle_deg >= criteria.min_angle_deg)
             & (ang_err_deg <= criteria.max_angular_error_deg))
    return Triangulation(points=points, valid=valid, in_front=in_front, angle_deg=angle_deg, range=rng,
                         angular_error_deg=ang_err_deg, finite=finite)


def _mid2_or_midpoint(f1, f2, c2, method: str) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and finite mask from unit rays f1 (camera 1) and f2 (camera 2, in camera 1's frame)."""
    cross = _cross(f1, f2)
    s2 = _rowdot(cross, cross)  # sin^2 of the angle between rays
    # Rays closer to parallel than ~1e-15 rad have no usable intersection in float64.
    finite = s2 > 1e-30
    s2_safe = np.where(finite, s2, 1.0)
    d = _rowdot(f1, f2)
    b1 = f1 @ c2
    b2 = f2 @ c2
    if method == "midpoint":
        # Closest points l1 f1 and c2 + l2 f2: the 2x2 normal equations in closed form.
        l1 = (b1 - d * b2) / s2_safe
        l2 = (d * b1 - b2) / s2_safe
    else:
        s = np.sqrt(s2_safe)
        # mid2's sine-rule depths are unsigned: divergent rays must be caught by cheirality.
        # Sign them by the midpoint solution so that rays meeting behind a camera stay behind.
        l1 = _rownorm(_cross(f2, c2[None])) / s * np.sign(np.where(finite, (b1 - d * b2), 1.0))
        l2 = _rownorm(_cross(f1, c2[None])) / s * np.sign(np.where(finite, (d * b1 - b2), 1.0))
    return 0.5 * (l1[:, None] * f1 + c2 + l2[:, None] * f2), finite


def _two_view_in_front_pm(r1, r2, R, t, max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Cheirality masks (`finite & in_front` of `triangulate_two_view`, mid2) for ``[R | t]`` and ``[R | -t]``.

    Flipping t negates c2, the signed mid2 depths and so every point and both camera depths exactly
    (IEEE negation commutes with rounding), so one triangulation decides both candidates; no angles
    are computed. The cheap part of choosing among an essential matrix's four decompositions.
    """
    c2 = -R.T @ t
    r2w = r2 @ R
    points, finite = _mid2_or_midpoint(_unit(r1), _unit(r2w), c2, "mid2")
    finite = finite & _finite_rows(points)
    points = np.where(finite[:, None], points, 0.0)
    rng = _rownorm(points)
    limit = max_range * max(float(np.linalg.norm(c2)), 1e-300)
    far = rng > limit
    if far.any():
        n = rng[:, None]
        points = np.where(far[:, None], limit * (points / np.where(n > 0, n, 1.0)), points)
    d1, d2 = points[:, 2], points @ R[2] + t[2]
    un1, un2 = ~_any_row(r1), ~_any_row(r2w)
    plus = finite & ((d1 > 0) | un1) & ((d2 > 0) | un2)
    minus = finite & ((d1 < 0) | un1) & ((d2 < 0) | un2)
    return plus, minus


def triangulate_two_view(
    rays1,
    rays2,
    cam2_from_cam1,
    *,
    method: Method = "mid2",
    criteria: TriangulationCriteria = DEFAULT_CRITERIA,
) -> Triangulation:
    """Triangulate N ray pairs of two cameras, in camera 1's frame.

    Args:
        rays1: (N, 3) ray directions in camera 1 (any positive length).
        rays2: (N, 3) ray directions in camera 2.
        cam2_from_cam1: (3, 4) or (4, 4).
        method: ``"mid2"`` (default), ``"midpoint"`` or ``"dlt"``.
        criteria: validity thresholds.

    Returns:
        `Triangulation` with points in camera 1's frame.

    Raises:
        DegenerateGeometryError: zero baseline (the cameras coincide); no
            point can be triangulated at all.
    """
    r1, r2, R, t, c2 = _two_view_setup(rays1, rays2, cam2_from_cam1)
    r2w = r2 @ R  # R^T r2: camera-2 rays in camera 1's frame
    if method in ("mid2", "midpoint"):
        points, finite = _mid2_or_midpoint(_unit(r1), _unit(r2w), c2, method)
    elif method == "dlt":
        P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
        P2 = np.hstack([R, t[:, None]])
        points, finite = _dlt(np.stack([r1, r2]), np.stack([P1, P2]), np.ones((2, r1.shape[0]), bool))
    else:
        raise ShapeError(f"method: expected 'mid2', 'midpoint' or 'dlt', got {method!r}")
    return _finalise_two_view(points, finite, c2, r1, r2w, criteria, R, t)


def _two_view_setup(rays1, rays2, cam2_from_cam1):
    """Checked rays, the relative pose and camera 2's centre in camera 1's frame (nonzero baseline)."""
    r1 = _check_rays(rays1, "rays1")
    r2 = _check_rays(rays2, "rays2")
    if r2.shape != r1.shape:
        raise ShapeError(f"rays2: expected shape {r1.shape}, got {r2.shape}")
    R, t = Rt_from_matrix(cam2_from_cam1)
    c2 = -R.T @ t  # camera 2 centre in camera 1's frame
    if not np.linalg.norm(c2) > 0:
        raise DegenerateGeometryError("triangulate_two_view: zero baseline (the camera centres coincide)")
    return r1, r2, R, t, c2


def _triangulate_two_view_reference(rays1, rays2, cam2_from_cam1, *, method: Method = "mid2",
                                    criteria: TriangulationCriteria = DEFAULT_CRITERIA) -> Triangulation:
    """Slow, obvious `triangulate_two_view` (np.cross and the V-generic `_finalise`): the tests' reference."""
    r1, r2, R, t, c2 = _two_view_setup(rays1, rays2, cam2_from_cam1)
    f1 = _unit(r1)
    f2 = _unit(r2 @ R)  # R^T r2: camera-2 rays in camera 1's frame
    if method in ("mid2", "midpoint"):
        cross = np.cross(f1, f2)
        s2 = np.sum(cross * cross, axis=-1)  # sin^2 of the angle between rays
        # Rays closer to parallel than ~1e-15 rad have no usable intersection in float64.
        finite = s2 > 1e-30
        s2_safe = np.where(finite, s2, 1.0)
        if method == "midpoint":
            # Closest points l1 f1 and c2 + l2 f2: solve the 2x2 normal equations in closed form.
            d = np.sum(f1 * f2, axis=-1)
            b1 = f1 @ c2
            b2 = f2 @ c2
            l1 = (b1 - d * b2) / s2_safe
            l2 = (d * b1 - b2) / s2_safe
        else:
            s = np.sqrt(s2_safe)
            l1 = np.linalg.norm(np.cross(f2, c2), axis=-1) / s
            l2 = np.linalg.norm(np.cross(f1, c2), axis=-1) / s
            # mid2's sine-rule depths are unsigned: divergent rays must be caught by cheirality.
            # Sign them by the midpoint solution so that rays meeting behind a camera stay behind.
            d = np.sum(f1 * f2, axis=-1)
            b1 = f1 @ c2
            b2 = f2 @ c2
            l1 = l1 * np.sign(np.where(finite, (b1 - d * b2), 1.0))
            l2 = l2 * np.sign(np.where(finite, (d * b1 - b2), 1.0))
        points = 0.5 * (l1[:, None] * f1 + c2 + l2[:, None] * f2)
    elif method == "dlt":
        P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
        P2 = np.hstack([R, t[:, None]])
        points, finite = _dlt(np.stack([r1, r2]), np.stack([P1, P2]), np.ones((2, r1.shape[0]), bool))
    else:
        raise ShapeError(f"method: expected 'mid2', 'midpoint' or 'dlt', got {method!r}")
    centres = np.stack([np.zeros(3), c2])
    rays_world = np.stack([r1, r2 @ R])
    return _finalise(points, finite, centres, rays_world, criteria,
                     np.stack([np.eye(3), R]), np.stack([np.zeros(3), t]))


def _dlt(rays: np.ndarray, P: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous DLT. rays (V, N, 3) in each camera; P (V, 3, 4); observed (V, N). Returns (N, 3), finite mask.

    The SVD of each point's system takes only its observed views' rows: the points are grouped by their
    number of views (a track is seen by a few of V views; the unobserved rows are zeros, which change neither
    the singular values nor the null vector, and `_dlt_reference` keeps them)."""
    V, N, _ = rays.shape
    r = _unit(rays)
    pts = np.zeros((N, 3))
    finite = np.zeros(N, bool)
    count = observed.sum(axis=0)
    order = np.argsort(count, kind="stable")
    views = np.argsort(~observed[:, order], axis=0, kind="stable").T  # per point (sorted): observed views first
    bounds = np.flatnonzero(np.diff(np.r_[-1, count[order], V + 1]))
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        L = int(count[order[lo]])
        idx = order[lo:hi]
        vs = views[lo:hi, :L]  # (n, L) the observed views of these points
        rows = np.einsum("nlij,nljk->nlik", _skew_rows(r[vs, idx[:, None]]), P[vs]).reshape(len(idx), 3 * L, 4)
        if L < 2:  # zero rows up to 6, so that the SVD reports the 4 singular values the uniqueness test reads
            rows = np.concatenate([rows, np.zeros((len(idx), 6 - 3 * L, 4))], axis=1)
        pts[idx], finite[idx] = _dlt_solve(rows)
    return pts, finite


def _skew_rows(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) [r]x of unit rays r (..., 3): each view's three rows of  [r]x P X = 0  (two are independent
    for r_z != 0; using all three avoids dividing by r_z)."""
    rx = np.zeros(r.shape[:-1] + (3, 3))
    rx[..., 0, 1], rx[..., 0, 2] = -r[..., 2], r[..., 1]
    rx[..., 1, 0], rx[..., 1, 2] = r[..., 2], -r[..., 0]
    rx[..., 2, 0], rx[..., 2, 1] = -r[..., 1], r[..., 0]
    return rx


def _dlt_solve(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points and finite mask from (n, rows, 4) homogeneous systems A X = 0 (the null vector by SVD)."""
    _, S, Vt = np.linalg.svd(A)
    X = Vt[:, -1]
    w = X[:, 3]
    xyz = X[:, :3]
    # Second-smallest singular value ~ 0: the solution is not unique (e.g. a single view).
    unique = S[:, -2] > 1e-12 * S[:, 0]
    finite = unique & (np.abs(w) > 1e-15 * np.linalg.norm(xyz, axis=-1))
    return xyz / np.where(finite, w, 1.0)[:, None], finite


def _dlt_reference(rays: np.ndarray, P: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slow, obvious `_dlt`: every point's system with all V views' rows (zeros where unobserved)."""
    V, N, _ = rays.shape
    r = _unit(rays)
    A = np.zeros((N, 3 * V, 4))
    for v in range(V):
        rows = _skew_rows(r[v]) @ P[v]
        A[:, 3 * v: 3 * v + 3] = np.where(observed[v][:, None, None], rows, 0.0)
    return _dlt_solve(A)


def triangulate_multiview(
    rays_cam,
    cam_from_world,
    *,
    observed=None,
    refine: bool = True,
    criteria: TriangulationCriteria = DEFAULT_CRITERIA,
) -> Triangulation:
    """Triangulate N points seen by up to V cameras (DLT, then Gauss–Newton on angular error).

    Args:
        rays_cam: (V, N, 3) observed ray directions in each camera's frame
            (rows of unobserved entries are ignored).
        cam_from_world: (V, 3, 4) or (V, 4, 4).
        observed: (V, N) bool, default all True. Points need >= 2 views.
        refine: polish the DLT estimate by minimising the sum of squared
            tangent-plane residuals of the unit rays (5 Gauss–Newton steps;
            this is the angular-error optimum to first order).
        criteria: validity thresholds.

    Returns:
        `Triangulation` with world-frame points; points with < 2 views are invalid.
    """
    rays = np.asarray(rays_cam, dtype=np.float64)
    check_shape(rays, ["V", "N", 3], "rays_cam")
    V, N, _ = rays.shape
    T = np.asarray(cam_from_world, dtype=np.float64)
    if T.shape[0] != V:
        raise ShapeError(f"cam_from_world: expected {V} poses, got shape {T.shape}")
    R, t = Rt_from_matrix(T)
    obs = np.ones((V, N), bool) if observed is None else np.asarray(observed, bool)
    check_shape(obs, [V, N], "observed")
    obs = obs & np.any(rays != 0, axis=-1)
    P = np.concatenate([R, t[..., None]], axis=-1)
    points, finite = _dlt(rays, P, obs)
    enough = obs.sum(axis=0) >= 2
    finite = finite & enough
    if refine:
        points = _refine_angular(points, finite, _unit(rays), R, t, obs)
    centres = -np.einsum("vji,vj->vi", R, t)
    rays_world = np.where(obs[..., None], np.einsum("vji,vnj->vni", R, rays), 0.0)
    return _finalise(points, finite, centres, rays_world, criteria, R, t)


def _refine_angular(points, finite, f, R, t, obs, iterations: int = 5):
    """Gauss–Newton on residuals e = (I - f f^T) (R X + t) / |R X + t| (sin of the angular error).

    Works on the observations only (a track is seen by a few of the V views; the dense (V, N)
    layout of `_refine_angular_reference`, the tests' reference, spends most of its time on
    unobserved entries) and accumulates each point's 3x3 normal equations by `np.bincount`.
    """
    N = points.shape[0]
    X = np.where(finite[:, None], points, 0.0)
    vk, nk = np.nonzero(obs)
    if len(vk) == 0:
        return np.where(finite[:, None], X, points)
    fk = f[vk, nk]  # (K, 3) unit observed rays
    Rk, tk = R[vk], t[vk]
    Pf = np.eye(3) - fk[:, :, None] * fk[:, None, :]  # (K, 3, 3)
    eye = np.eye(3)
    for _ in range(iterations):
        Y = np.matmul(Rk, X[nk][:, :, None])[:, :, 0] + tk
        n = np.sqrt(np.sum(Y * Y, axis=-1))[:, None]
        n = np.where(n > 0, n, 1.0)
        u = Y / n
        e = np.matmul(Pf, u[:, :, None])[:, :, 0]
        # d u / d Y = (I - u u^T) / |Y|;  d Y / d X = R
        du = (eye - u[:, :, None] * u[:, None, :]) / n[:, :, None]
        J = np.matmul(np.matmul(Pf, du), Rk)  # (K, 3, 3)
        Hk = np.matmul(J.transpose(0, 2, 1), J).reshape(-1, 9)
        gk = np.matmul(J.transpose(0, 2, 1), e[:, :, None])[:, :, 0]
        H = np.stack([np.bincount(nk, Hk[:, a], minlength=N) for a in range(9)], -1).reshape(N, 3, 3)
        g = np.stack([np.bincount(nk, gk[:, a], minlength=N) for a in range(3)], -1)
        H = H + 1e-12 * np.trace(H, axis1=-2, axis2=-1)[:, None, None] * eye
        ok = finite & (np.abs(np.linalg.det(H)) > 0)
        H_safe = np.where(ok[:, None, None], H, eye)
        step = np.linalg.solve(H_safe, g[..., None])[..., 0]
        X = np.where(ok[:, None], X - step, X)
    return np.where(finite[:, None], X, points)


def _refine_angular_reference(points, finite, f, R, t, obs, iterations: int = 5):
    """Gauss–Newton on residuals e_v = (I - f f^T) (R X + t) / |R X + t| (sin of the angular error)."""
    X = np.where(finite[:, None], points, 0.0)
    for _ in range(iterations):
        Y = np.einsum("vij,nj->vni", R, X) + t[:, None]  # (V, N, 3)
        n = np.linalg.norm(Y, axis=-1, keepdims=True)
        n = np.where(n > 0, n, 1.0)
        u = Y / n
        Pf = np.eye(3) - f[..., :, None] * f[..., None, :]  # (V, N, 3, 3)
        e = np.einsum("vnij,vnj->vni", Pf, u)
        # d u / d Y = (I - u u^T) / |Y|;  d Y / d X = R
        du = (np.eye(3) - u[..., :, None] * u[..., None, :]) / n[..., None]
        J = np.einsum("vnij,vnjk,vkl->vnil", Pf, du, R)
        w = obs[..., None, None].astype(float)
        H = np.einsum("vnji,vnjk->nik", J * w, J)
        g = np.einsum("vnji,vnj->ni", J * w, e)
        H = H + 1e-12 * np.trace(H, axis1=-2, axis2=-1)[:, None, None] * np.eye(3)
        ok = finite & (np.abs(np.linalg.det(H)) > 0)
        H_safe = np.where(ok[:, None, None], H, np.eye(3))
        step = np.linalg.solve(H_safe, g[..., None])[..., 0]
        X = np.where(ok[:, None], X - step, X)
    return np.where(finite[:, None], X, points)


def triangulate_views_px(
    uv_px,
    cameras,
    cam_from_world,
    *,
    observed=None,
    criteria: TriangulationCriteria = DEFAULT_CRITERIA,
) -> Triangulation:
    """Triangulate pixel observations through `Camera` models (unproject, multi-view, reproject).

    Adds ``reprojection_error_px`` (max over observing views) to the validity;
    observations whose unprojection fails are treated as unobserved.

    Args:
        uv_px: (V, N, 2) pixel coordinates (our convention).
        cameras: sequence of V `mvgeo.camera.Camera`.
        cam_from_world: (V, 3, 4) or (V, 4, 4).
        observed: (V, N) bool, default all True.
        criteria: validity thresholds.

    Returns:
        `Triangulation` with world-frame points and reprojection errors.
    """
    uv = np.asarray(uv_px, dtype=np.float64)
    check_shape(uv, ["V", "N", 2], "uv_px")
    V, N, _ = uv.shape
    if len(cameras) != V:
        raise ShapeError(f"cameras: expected {V} cameras, got {len(cameras)}")
    obs = np.ones((V, N), bool) if observed is None else np.asarray(observed, bool)
    check_shape(obs, [V, N], "observed")
    rays = np.zeros((V, N, 3))
    for v, cam in enumerate(cameras):
        un = cam.unproject(uv[v])
        rays[v] = np.where(un.valid[:, None], un.rays_cam, 0.0)
        obs[v] &= un.valid
    tri = triangulate_multiview(rays, cam_from_world, observed=obs, criteria=criteria)
    R, t = Rt_from_matrix(np.asarray(cam_from_world, dtype=np.float64))
    err = np.zeros(N)
    for v, cam in enumerate(cameras):
        pr = cam.project(tri.points @ R[v].T + t[v])
        e = np.linalg.norm(pr.uv_px - uv[v], axis=-1)
        e = np.where(pr.valid, e, np.inf)
        err = np.where(obs[v], np.maximum(err, e), err)
    err = np.where(np.isfinite(err), err, 1e300)
    valid = tri.valid & (err <= criteria.max_reprojection_error_px)
    return Triangulation(
        points=tri.points, valid=valid, in_front=tri.in_front, angle_deg=tri.angle_deg, range=tri.range,
        angular_error_deg=tri.angular_error_deg, finite=tri.finite, reprojection_error_px=err,
    )

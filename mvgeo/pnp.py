"""Absolute pose (PnP) with RANSAC and our own Levenberg–Marquardt refinement (numpy float64).

`estimate_absolute_pose` unprojects the pixels through the `Camera` model
(so distortion is handled exactly), runs OpenCV's ``solvePnPRansac`` (P3P
minimal solver, on normalised coordinates with the threshold converted from
pixels) to get a pose and inliers, then refines ``cam_from_world`` with
`refine_pose_lm`, which minimises the reprojection error **in pixels through
the full camera model** using analytic Jacobians
(``d uv / d pose = d uv / d X_cam @ [-[X_cam]_x | I]`` for the left
perturbation ``cam_from_world <- se3_exp(delta) @ cam_from_world``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import ShapeError, check_shape
from mvgeo.ransac import RansacConfig
from mvgeo.transforms import R_from_axis_angle, se3_exp, skew

__all__ = ["PnPConfig", "AbsolutePoseResult", "estimate_absolute_pose", "refine_pose_lm", "LMResult", "sqpnp",
           "sqpnp_ransac"]


def sqpnp(obj: np.ndarray, uv_cv: np.ndarray, K_cv: np.ndarray) -> tuple[bool, np.ndarray | None, np.ndarray | None]:
    """`cv2.solvePnP` with SQPnP: ``(ok, rvec, tvec)``, ``(False, None, None)`` where OpenCV rejects the points.

    SQPnP asserts (OpenCV 5.0.0: ``point_coordinate_variance >= POINT_VARIANCE_THRESHOLD``) instead of
    failing when the points nearly coincide; that is a degenerate input, not an error of the caller.

    Args:
        obj: (N, 3) float64 world points; uv_cv: (N, 2) float64 pixels in OpenCV's convention (centres at
            integers); K_cv: (3, 3) intrinsics in that convention.
    """
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, uv_cv, K_cv, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return False, None, None
    return bool(ok), rvec, tvec


def sqpnp_ransac(obj: np.ndarray, uv_cv: np.ndarray, K_cv: np.ndarray, *, reprojection_px: float, iterations: int,
                 confidence: float) -> tuple[bool, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """`cv2.solvePnPRansac` with SQPnP: ``(ok, rvec, tvec, inliers)``; ``(False, None, None, None)`` where
    OpenCV rejects the points (SQPnP's assertion on nearly coinciding points, as `sqpnp`; met on a real
    set where many keypoints matched one triangulated point). Arguments as `sqpnp`, plus RANSAC's."""
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(obj, uv_cv, K_cv, None, reprojectionError=reprojection_px,
                                                     iterationsCount=iterations, confidence=confidence,
                                                     flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return False, None, None, None
    return bool(ok), rvec, tvec, inliers


@dataclass(frozen=True)
class PnPConfig:
    """Options of `estimate_absolute_pose`.

    Attributes:
        ransac: ``threshold_px`` is the reprojection-error threshold in pixels;
            ``seed`` seeds OpenCV's RNG (``cv2.setRNGSeed``) for repeatable sampling.
        min_inliers: fewer -> ``success=False``.
        lm_iterations: maximum LM iterations of the refinement.
    """

    ransac: RansacConfig = field(default_factory=lambda: RansacConfig(threshold_px=2.0))
    min_inliers: int = 6
    lm_iterations: int = 50


@dataclass(frozen=True)
class LMResult:
    """Outcome of `refine_pose_lm`.

    Attributes:
        cam_from_world: (3, 4) refined pose.
        rmse_px: final RMS reprojection error over the used points.
        initial_rmse_px: before refinement.
        iterations: LM iterations run.
        converged: the relative cost decrease or step fell below tolerance.
    """

    cam_from_world: np.ndarray
    rmse_px: float
    initial_rmse_px: float
    iterations: int
    converged: bool


@dataclass(frozen=True)
class AbsolutePoseResult:
    """Camera pose from 2-D/3-D matches, with validity.

    Attributes:
        success: at least ``min_inliers`` inliers for the refined pose (the refinement's convergence is
            not required: it may stop at ``lm_iterations``; the inliers are re-selected with its pose).
        reason: empty on success, else why not.
        cam_from_world: (3, 4) (identity when nothing was found).
        inlier_mask: (N,) bool, reprojection error < threshold for the final pose.
        n_inliers: ``inlier_mask.sum()``.
        rmse_px: RMS reprojection error over the inliers.
    """

    success: bool
    reason: str
    cam_from_world: np.ndarray
    inlier_mask: np.ndarray
    n_inliers: int
    rmse_px: float


def _residuals(cam_from_world, points_world, uv_px, camera, with_jac: bool):
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    Xc = points_world @ R.T + t
    pr = camera.project(Xc, with_jacobians=with_jac)
    r = (pr.uv_px - uv_px).reshape(-1)
    if not with_jac:
        return r, pr.valid, None
    d_X_d_xi = np.concatenate([-skew(Xc), np.broadcast_to(np.eye(3), Xc.shape[:-1] + (3, 3))], axis=-1)
    J = (pr.d_uv_d_point @ d_X_d_xi).reshape(-1, 6)
    return r, pr.valid, J


def refine_pose_lm(
    cam_from_world, points_world, uv_px, camera: Camera, *, max_iterations: int = 50, tol: float = 1e-12
) -> LMResult:
    """Minimise the squared reprojection error over the pose with Levenberg–Marquardt.

    Args:
        cam_from_world: (3, 4) or (4, 4) initial pose.
        points_world: (N, 3) world points, N >= 3.
        uv_px: (N, 2) observations (our pixel convention).
        camera: intrinsics (held fixed).
        max_iterations: LM iterations.
        tol: stop when the relative cost decrease and the step norm fall below this.

    Returns:
        `LMResult`.
    """
    T = np.asarray(cam_from_world, dtype=np.float64)[:3].copy()
    X = np.asarray(points_world, dtype=np.float64)
    uv = np.asarray(uv_px, dtype=np.float64)
    check_shape(X, ["N", 3], "points_world")
    check_shape(uv, [X.shape[0], 2], "uv_px")
    r, valid, J = _residuals(T, X, uv, camera, True)
    cost = float(r @ r)
    initial = np.sqrt(cost / max(len(X), 1))
    lam = 1e-3
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007
        JtJ = J.T @ J
        g = J.T @ r
        improved = False
        for _ in range(10):
            A = JtJ + lam * np.diag(np.maximum(np.diag(JtJ), 1e-12))
            try:
                delta = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            T_new = (se3_exp(delta) @ np.vstack([T, [0, 0, 0, 1]]))[:3]
            r_new, valid_new, J_new = _residuals(T_new, X, uv, camera, True)
            cost_new = float(r_new @ r_new)
            # Accept only descent steps that do not push a point behind the camera / out of the lens model.
            if np.isfinite(cost_new) and cost_new < cost and (valid_new.all() or not valid.all()):
                rel = (cost - cost_new) / max(cost, 1e-300)
                T, r, valid, J, cost = T_new, r_new, valid_new, J_new, cost_new
                lam = max(lam / 10, 1e-12)
                improved = True
                if rel < tol or np.linalg.norm(delta) < tol:
                    converged = True
                break
            lam *= 10
        if not improved:
            converged = True  # no descent step exists at this damping: a (local) minimum
            break
        if converged:
            break
    return LMResult(cam_from_world=T, rmse_px=float(np.sqrt(cost / max(len(X), 1))), initial_rmse_px=float(initial),
                    iterations=it, converged=converged)


def estimate_absolute_pose(
    uv_px, points_world, camera: Camera, *, config: PnPConfig | None = None
) -> AbsolutePoseResult:
    """Robust PnP: OpenCV P3P-RANSAC on unprojected rays, then our LM refinement on the inliers.

    Args:
        uv_px: (N, 2) pixel observations (our convention), N >= 4.
        points_world: (N, 3) matching world points.
        camera: intrinsics, any supported model.
        config: `PnPConfig`.

    Returns:
        `AbsolutePoseResult`.
    """
    config = config or PnPConfig()
    uv = np.asarray(uv_px, dtype=np.float64)
    X = np.asarray(points_world, dtype=np.float64)
    check_shape(uv, ["N", 2], "uv_px")
    check_shape(X, [uv.shape[0], 3], "points_world")
    n = len(uv)
    fail = AbsolutePoseResult(False, "", np.eye(4)[:3], np.zeros(n, bool), 0, float("inf"))
    if n < 4:
        return AbsolutePoseResult(**{**fail.__dict__, "reason": f"need >= 4 matches, got {n}"})
    finite = np.all(np.isfinite(uv), axis=1) & np.all(np.isfinite(X), axis=1)
    if not finite.all():
        raise ShapeError(f"uv_px/points_world: {np.count_nonzero(~finite)} non-finite entries")
    un = camera.unproject(uv)
    usable = np.flatnonzero(un.valid)
    if len(usable) < 4:
        return AbsolutePoseResult(**{**fail.__dict__, "reason": "fewer than 4 pixels could be unprojected"})
    f = 0.5 * (camera.fx + camera.fy)
    cv2.setRNGSeed(int(config.ransac.seed))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X[usable], un.rays_cam[usable, :2], np.eye(3), None,
        iterationsCount=int(config.ransac.max_iterations), reprojectionError=config.ransac.threshold_px / f,
        confidence=config.ransac.confidence, flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or inl is None or len(inl) < 4:
        return AbsolutePoseResult(**{**fail.__dict__, "reason": "OpenCV solvePnPRansac found no pose"})
    T = np.c_[R_from_axis_angle(rvec.ravel()), tvec.ravel()]
    idx = usable[inl.ravel()]
    for _ in range(2):  # refine on inliers, re-select inliers, refine again
        lm = refine_pose_lm(T, X[idx], uv[idx], camera, max_iterations=config.lm_iterations)
        T = lm.cam_from_world
        r, valid, _ = _residuals(T, X, uv, camera, False)
        err = np.linalg.norm(r.reshape(-1, 2), axis=1)
        inliers = valid & (err < config.ransac.threshold_px)
        if inliers.sum() < 4:
            break
        idx = np.flatnonzero(inliers)
    rmse = float(np.sqrt(np.mean(err[inliers] ** 2))) if inliers.any() else float("inf")
    reason = ""
    if inliers.sum() < config.min_inliers:
        reason = f"only {int(inliers.sum())} inliers (< min_inliers={config.min_inliers})"
    return AbsolutePoseResult(success=reason == "", reason=reason, cam_from_world=T, inlier_mask=inliers,
                              n_inliers=int(inliers.sum()), rmse_px=rmse)

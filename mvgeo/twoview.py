"""Robust relative pose from two views (numpy float64): calibrated and shared-unknown-focal.

Both estimators take pixel matches in our convention (top-left pixel centre
at (0.5, 0.5), docs/conventions.md) and return a `RelativePoseResult` with
``cam2_from_cam1 = [R | t]``, ``|t| = 1`` (scale is unobservable), inlier
mask and explicit validity: ``success`` is False, with a ``reason``, when
too few inliers survive, when the baseline is too small for the translation
to mean anything (pure rotation gives tiny triangulation angles), when — for
the uncalibrated estimator — a homography explains the matches (planar
scene or pure rotation: F and the focal length are then not determined), or
when — for the calibrated one — the scene is planar and two relative poses
explain the matches and put them in front of both cameras alike.

Pipeline (own implementation; OpenCV's USAC is available as ``backend="opencv"``
and is the reference in the tests):

1. Seeded LO-MSAC (`mvgeo.ransac`) with our minimal solvers
   (`mvgeo.epipolar.essential_5point`, `fundamental_7point`), scored by the
   Sampson distance **in pixels**, LO with the linear 8-point solver.
2. Pose from E: the four decompositions, cheirality by Lee–Civera mid2
   triangulation of the inliers (`mvgeo.triangulate`).
3. Levenberg–Marquardt refinement of ``(R, t)`` (and ``log f``) on the
   inliers' Sampson distances (scipy ``least_squares``), then inliers are
   re-selected with the refined model.

Focal length from F (uncalibrated, shared focal, principal point at the
image centre): a 1-D search over ``f`` minimising the essential-matrix
singular-value gap ``(s1 - s2) / (s1 + s2)`` of ``E(f) = K(f)^T F K(f)``
(a coarse log grid, then bounded Brent), followed by the joint LM above. We
do not use Bougnoux's closed form: it returns ``f^2 < 0`` under noise and is
singular whenever the optical axes are coplanar (two cameras looking at a
common point, i.e. every object-centric capture), while the search always
returns a positive focal. No method escapes the true ambiguity (Sturm 2001:
optical axes meeting at a point equidistant from both centres, e.g. a
turntable), so the result carries ``focal_rel_std`` from the LM covariance
and ``focal_well_determined``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from mvgeo.common.deps import cv2
from mvgeo.common.errors import ShapeError, check_shape
from mvgeo.epipolar import (
    decompose_essential,
    essential_5point,
    essential_from_linear,
    essential_from_pose,
    fundamental_7point,
    fundamental_8point,
    fundamental_from_essential,
    project_to_essential,
    sampson_distance,
)
from mvgeo.metrics import rotation_error_deg
from mvgeo.ransac import RansacConfig, ransac
from mvgeo.transforms import skew_unchecked, so3_exp_and_left_jacobian
from mvgeo.triangulate import TriangulationCriteria, _two_view_in_front_pm, triangulate_two_view

__all__ = [
    "TwoViewConfig",
    "RelativePoseResult",
    "FocalEstimate",
    "estimate_relative_pose",
    "estimate_relative_pose_uncalibrated",
    "relative_rotation_std_deg",
    "estimate_fundamental",
    "focal_from_fundamental",
    "pose_from_essential",
]


@dataclass(frozen=True)
class TwoViewConfig:
    """Options of the two-view estimators.

    Attributes:
        ransac: sampling options; ``ransac.threshold_px`` is the Sampson
            distance threshold in pixels.
        min_inliers: fewer inliers than this -> ``success=False``.
        min_median_angle_deg: median parallax (rotation-compensated ray angle) of the inliers below
            this -> ``success=False`` (pure rotation / too small a baseline).
        max_homography_ratio: uncalibrated only: if a homography has at least
            this fraction of F's inliers the scene is planar or the motion a
            pure rotation -> ``success=False``.
        planar_rival_front: calibrated only: where a homography explains the inliers as well as the
            essential matrix does (a planar scene; `_resolve_planar`), its second pose putting at least
            this fraction of the first one's count of inliers in front of both cameras -> ``success=False``
            (the two poses are not told apart).
        refine: run the final Levenberg–Marquardt refinement.
        focal_search_range: focal search interval as multiples of ``max(W, H)``
            (0.2 .. 5 covers ~170 deg down to ~11 deg horizontal field of view).
        max_focal_rel_std: ``focal_well_determined`` requires the LM relative
            standard deviation of ``f`` below this.
        noise_floor_px: measurement noise assumed at least this large when
            computing ``focal_rel_std`` (so exact synthetic data cannot make a
            degenerate geometry look well determined).
        backend: ``"own"`` (default) or ``"opencv"`` (``cv2.findEssentialMat`` /
            ``findFundamentalMat`` with USAC_MAGSAC, its model refit on the consensus set it reports when it
            explains less than half of that set, then steps 2-3 above).
    """

    ransac: RansacConfig = field(default_factory=RansacConfig)
    min_inliers: int = 15
    min_median_angle_deg: float = 0.5
    max_homography_ratio: float = 0.9
    planar_rival_front: float = 0.95
    refine: bool = True
    focal_search_range: tuple[float, float] = (0.2, 5.0)
    max_focal_rel_std: float = 0.05
    noise_floor_px: float = 0.1
    backend: Literal["own", "opencv"] = "own"


@dataclass(frozen=True)
class RelativePoseResult:
    """Relative pose ``cam2_from_cam1`` from matches, with validity.

    Attributes:
        success: True when the pose can be trusted (see `TwoViewConfig`).
        reason: empty on success, else why not.
        R: (3, 3) rotation (identity when nothing was found).
        t: (3,) unit translation (zeros when nothing was found).
        E: (3, 3) essential matrix (normalised coordinates, unit norm).
        F: (3, 3) fundamental matrix on our pixel coordinates (unit norm).
        inlier_mask: (N,) bool, Sampson distance < threshold for the final model.
        n_inliers: ``inlier_mask.sum()``.
        in_front_mask: (N,) bool, inliers triangulating in front of both cameras.
        median_angle_deg: median parallax of the inliers: angle between the
            rotation-compensated rays ``f1`` and ``R^T f2`` (the triangulation
            angle for intersecting rays; independent of ``t``).
        iterations: RANSAC samples drawn.
        focal_px: shared focal length (uncalibrated estimator), else None.
        focal_rel_std: relative standard deviation of ``focal_px`` (LM covariance), else None.
        focal_well_determined: ``focal_rel_std <= max_focal_rel_std`` (uncalibrated only).
        homography_ratio: homography inliers / F inliers (uncalibrated only).
    """

    success: bool
    reason: str
    R: np.ndarray
    t: np.ndarray
    E: np.ndarray
    F: np.ndarray
    inlier_mask: np.ndarray
    n_inliers: int
    in_front_mask: np.ndarray
    median_angle_deg: float
    iterations: int
    focal_px: float | None = None
    focal_rel_std: float | None = None
    focal_well_determined: bool | None = None
    homography_ratio: float | None = None


@dataclass(frozen=True)
class FocalEstimate:
    """Shared focal length from a fundamental matrix.

    Attributes:
        focal_px: minimiser of the singular-value gap on the search interval.
        cost: ``(s1 - s2) / (s1 + s2)`` at ``focal_px`` (0 for an exact F).
        at_bound: the minimum lies on the search interval's boundary (suspect).
    """

    focal_px: float
    cost: float
    at_bound: bool


def _check_matches(uv1, uv2) -> tuple[np.ndarray, np.ndarray]:
    u1 = np.asarray(uv1, dtype=np.float64)
    u2 = np.asarray(uv2, dtype=np.float64)
    check_shape(u1, ["N", 2], "uv1_px")
    check_shape(u2, [u1.shape[0], 2], "uv2_px")
    ok = np.all(np.isfinite(u1), axis=1) & np.all(np.isfinite(u2), axis=1)
    if not ok.all():
        raise ShapeError(f"uv1_px/uv2_px: {np.count_nonzero(~ok)} non-finite coordinates")
    return u1, u2


def _to_norm(u: np.ndarray, K: np.ndarray) -> np.ndarray:
    Kinv = np.linalg.inv(K)
    return u @ Kinv[:2, :2].T + Kinv[:2, 2]


def _failure(n: int, reason: str, iterations: int = 0, **extra) -> RelativePoseResult:
    z = np.zeros(n, bool)
    return RelativePoseResult(
        success=False, reason=reason, R=np.eye(3), t=np.zeros(3), E=np.zeros((3, 3)), F=np.zeros((3, 3)),
        inlier_mask=z, n_inliers=0, in_front_mask=z.copy(), median_angle_deg=0.0, iterations=iterations, **extra,
    )


#: OpenCV's USAC model is refit on the consensus set it reports when it explains (Sampson distance below the
#: threshold, in pixels) fewer than this fraction of that set (`estimate_relative_pose`, `estimate_fundamental`).
_USAC_MIN_EXPLAINED = 0.5

_CHEIRALITY = TriangulationCriteria(min_angle_deg=0.0, max_angular_error_deg=180.0, max_range=1e8)


def pose_from_essential(E, x1, x2) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Choose among the four decompositions of E by cheirality (mid2 triangulation).

    Args:
        E: (3, 3).
        x1: (N, 2) normalised coordinates, camera 1 (typically the inliers).
        x2: (N, 2) camera 2.

    Returns:
        ``R (3, 3)``, ``t (3,)`` unit, ``in_front (N,)`` bool, ``angle_deg (N,)``.
    """
    Rs, ts = decompose_essential(E)
    r1 = np.c_[x1, np.ones(len(x1))]
    r2 = np.c_[x2, np.ones(len(x2))]
    # Candidates (R1, t), (R1, -t), (R2, t), (R2, -t): one triangulation per rotation decides both signs
    # of t; the winner (first with the most points in front) is triangulated in full for its angles.
    # `_pose_from_essential_reference` (four full triangulations) is the tests' reference.
    fronts = []
    for k in (0, 2):
        fronts.extend(_two_view_in_front_pm(r1, r2, Rs[k], ts[k], _CHEIRALITY.max_range))
    counts = [int(f.sum()) for f in fronts]
    k = counts.index(max(counts))
    tri = triangulate_two_view(r1, r2, np.c_[Rs[k], ts[k]], method="mid2", criteria=_CHEIRALITY)
    return Rs[k], ts[k], tri.in_front & tri.finite, tri.angle_deg


def _pose_from_essential_reference(E, x1, x2):
    """Slow, obvious `pose_from_essential`: a full triangulation of each of the four candidates."""
    Rs, ts = decompose_essential(E)
    r1 = np.c_[x1, np.ones(len(x1))]
    r2 = np.c_[x2, np.ones(len(x2))]
    best = None
    for R, t in zip(Rs, ts, strict=True):
        tri = triangulate_two_view(r1, r2, np.c_[R, t], method="mid2", criteria=_CHEIRALITY)
        front = tri.in_front & tri.finite
        if best is None or front.sum() > best[2].sum():
            best = (R, t, front, tri.angle_deg)
    return best


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane orthogonal to unit t."""
    a = np.eye(3)[np.argmin(np.abs(t))]
    b1 = np.cross(t, a)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(t, b1)], axis=1)


class _SampsonProblem:
    """Signed Sampson distances (pixels) of matches under ``F = K2^-T [t]_x R K1^-1`` and their exact
    Jacobian, for `_refine`'s parameters ``p = ([log-focal change], rotation increment (3), translation
    increment in the tangent plane (2))``.

    ``R = exp(w) R0``, ``t = (t0 + B b) / |t0 + B b|``; with a focal, ``K1 = K2 = K(f0 exp(p[0]))`` with the
    principal point `principal_px`. The residual's derivative in F is analytic, and F's in p is analytic
    (the left Jacobian of SO(3) for the rotation, the projection onto the unit sphere for t, and
    ``d K^-1 / d log f = -(K^-1 with its last row zeroed)`` for the focal).
    """

    def __init__(self, u1, u2, K1, K2, R0, t0, log_f0, principal_px):
        self.h1 = np.c_[u1, np.ones(len(u1))]
        self.h2 = np.c_[u2, np.ones(len(u2))]
        self.R0, self.t0, self.B = R0, t0, _tangent_basis(t0)
        self.log_f0, self.c = log_f0, principal_px
        self.K1i, self.K2i = (None, None) if log_f0 is not None else (np.linalg.inv(K1), np.linalg.inv(K2))
        self.n_f = 0 if log_f0 is None else 1
        self._cache: tuple[bytes, tuple] | None = None

    def unpack(self, p):
        """(w, R, t, |t0 + B b|, log f or None) of parameters `p`."""
        return self._unpack(p)[:5]

    def _unpack(self, p):
        n_f = self.n_f
        w = p[n_f:n_f + 3]
        Rw, Jl = so3_exp_and_left_jacobian(w)
        tu = self.t0 + self.B @ p[n_f + 3:n_f + 5]
        norm = float(np.sqrt(tu @ tu))
        lf = None if self.log_f0 is None else self.log_f0 + p[0]
        return w, Rw @ self.R0, tu / norm, norm, lf, Jl

    def _Kinv(self, lf):
        if lf is None:
            return self.K1i, self.K2i
        f = np.exp(lf)
        Ki = np.array([[1.0 / f, 0.0, -self.c[0] / f], [0.0, 1.0 / f, -self.c[1] / f], [0.0, 0.0, 1.0]])
        return Ki, Ki

    def _eval(self, p):
        key = p.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        w, R, t, norm, lf, Jl = self._unpack(p)
        K1i, K2i = self._Kinv(lf)
        E = skew_unchecked(t) @ R
        F = K2i.T @ E @ K1i
        Fx1 = self.h1 @ F.T
        Ftx2 = self.h2 @ F
        num = (self.h2 * Fx1).sum(axis=1)
        den = np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
        den = np.maximum(den, 1e-300)
        out = (R, t, norm, lf, Jl, K1i, K2i, E, Fx1, Ftx2, num, den)
        self._cache = (key, out)
        return out

    def residuals(self, p) -> np.ndarray:
        *_, num, den = self._eval(p)
        return num / den

    def jacobian(self, p) -> np.ndarray:
        R, t, norm, lf, Jl, K1i, K2i, E, Fx1, Ftx2, num, den = self._eval(p)
        # dF / dp_k, (n_p, 3, 3): the focal's, then [t]_x [J_l e_k]_x R (rotation), then
        # [P B e_m]_x R with P the projection onto the sphere's tangent plane at t (translation).
        P = (np.eye(3) - np.outer(t, t)) / norm
        M = np.concatenate([skew_unchecked(t) @ skew_unchecked(Jl.T) @ R, skew_unchecked((P @ self.B).T) @ R])
        dF = K2i.T @ M @ K1i
        if lf is not None:
            D = K1i.copy()
            D[2] = 0.0
            dF = np.concatenate([-(D.T @ E @ K1i + K2i.T @ E @ D)[None], dF])
        # r = num / den with num = h2^T F h1 and den^2 = (F h1)_0^2 + (F h1)_1^2 + (F^T h2)_0^2 + (F^T h2)_1^2:
        # dr = dnum / den - num / (2 den^3) dden2, each along dF_k.
        n, k = len(self.h1), len(dF)
        G1 = (self.h1 @ dF.reshape(3 * k, 3).T).reshape(n, k, 3)  # dF_k h1
        G2 = (self.h2 @ dF.transpose(1, 0, 2).reshape(3, 3 * k)).reshape(n, k, 3)  # dF_k^T h2
        dnum = (G1 * self.h2[:, None, :]).sum(axis=2)
        dden2 = 2.0 * (Fx1[:, None, 0] * G1[:, :, 0] + Fx1[:, None, 1] * G1[:, :, 1]
                       + Ftx2[:, None, 0] * G2[:, :, 0] + Ftx2[:, None, 1] * G2[:, :, 1])
        return dnum / den[:, None] - (num / (2.0 * den**3))[:, None] * dden2


def _refine(u1, u2, K1, K2, R0, t0, noise_floor_px: float, *, log_f0: float | None = None,
            principal_px: tuple[float, float] | None = None):
    """LM on signed Sampson distances (pixels) with an exact Jacobian (`_SampsonProblem`).

    Without `log_f0` the cameras are `K1`, `K2`; with it, both are ``K(exp(log f))`` with `principal_px`
    and the log-focal is refined too. Returns R, t, f (or None), rel_std of f (or None).
    """
    prob = _SampsonProblem(u1, u2, K1, K2, R0, t0, log_f0, principal_px)
    sol = least_squares(prob.residuals, np.zeros(prob.n_f + 5), jac=prob.jacobian, method="lm", x_scale="jac",
                        max_nfev=200)
    _, R, t, _, lf = prob.unpack(sol.x)
    rel_std = None
    if log_f0 is not None:
        J = sol.jac
        m = len(u1)
        sigma2 = max(float(np.sum(sol.fun**2)) / max(m - J.shape[1], 1), noise_floor_px**2)
        JtJ = J.T @ J
        try:
            cov = np.linalg.inv(JtJ) * sigma2
            rel_std = float(np.sqrt(cov[0, 0])) if cov[0, 0] >= 0 and np.isfinite(cov[0, 0]) else np.inf
        except np.linalg.LinAlgError:
            rel_std = np.inf
        # A near-singular J^T J (degenerate geometry) shows up as a huge variance; cap at inf.
        if np.linalg.cond(JtJ) > 1e14:
            rel_std = np.inf
    return R, t, (None if lf is None else float(np.exp(lf))), rel_std


def relative_rotation_std_deg(uv1_px: np.ndarray, uv2_px: np.ndarray, K1: np.ndarray, K2: np.ndarray, R: np.ndarray,
                              t: np.ndarray, *, inlier_px: float = 2.0, noise_floor_px: float = 0.25) -> float:
    """How well a pair's matches pin its relative rotation at the pose (R, t) (cam2_from_cam1; t's norm ignored):
    the largest standard deviation (deg) of the rotation, from the Gauss-Newton covariance of the five-parameter
    relative pose on the matches' Sampson distances (pixels) within `inlier_px`, their noise taken as their RMS
    but at least `noise_floor_px`. A linearisation: along a bas-relief valley (narrow field of view, few matches)
    the true uncertainty is larger still. inf with fewer than 6 such matches or a singular system."""
    u1, u2 = _check_matches(uv1_px, uv2_px)
    t = np.asarray(t, np.float64)
    prob = _SampsonProblem(u1, u2, np.asarray(K1, np.float64), np.asarray(K2, np.float64), np.asarray(R, np.float64),
                           t / np.linalg.norm(t), None, None)
    p0 = np.zeros(5)
    r = prob.residuals(p0)
    keep = np.abs(r) < inlier_px
    if keep.sum() < 6:
        return float("inf")
    r, J = r[keep], prob.jacobian(p0)[keep]
    sigma2 = max(float(r @ r) / (len(r) - 5), noise_floor_px**2)
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)) or np.linalg.cond(JtJ) > 1e14:
        return float("inf")
    cov = np.linalg.inv(JtJ)[:3, :3] * sigma2
    return float(np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(cov).max()), 0.0))))


def _finish(u1, u2, K1, K2, E, ransac_inliers, iterations, config, *, extra=None) -> RelativePoseResult:
    """Cheirality, refinement, inlier re-selection and validity for a calibrated pair."""
    n = len(u1)
    extra = dict(extra or {})
    thr = config.ransac.threshold_px
    x1, x2 = _to_norm(u1, K1), _to_norm(u2, K2)
    idx = np.flatnonzero(ransac_inliers)
    R, t, _, _ = pose_from_essential(E, x1[idx], x2[idx])
    inliers = ransac_inliers
    # Refine on the inliers, re-select them with the refined model, repeat until the set is stable.
    for _ in range(3 if config.refine else 0):
        if len(idx) < 6:
            break
        R, t, _, _ = _refine(u1[idx], u2[idx], K1, K2, R, t, config.noise_floor_px)
        new = sampson_distance(fundamental_from_essential(essential_from_pose(R, t), K1, K2), u1, u2) < thr
        stable = np.array_equal(new, inliers)
        inliers = new
        idx = np.flatnonzero(inliers)
        if stable:
            break
    E = essential_from_pose(R, t)
    E = E / np.linalg.norm(E)
    F = fundamental_from_essential(E, K1, K2)
    inliers = sampson_distance(F, u1, u2) < thr
    idx = np.flatnonzero(inliers)
    tri = triangulate_two_view(np.c_[x1[idx], np.ones(len(idx))], np.c_[x2[idx], np.ones(len(idx))], np.c_[R, t],
                               method="mid2", criteria=_CHEIRALITY)
    front_idx = tri.in_front & tri.finite
    in_front = np.zeros(n, bool)
    in_front[idx[front_idx]] = True
    # Parallax = angle between the rotation-compensated rays; it does not depend on t, so it also
    # measures pure rotation (where any t fits and the triangulated points are meaningless).
    f1 = np.c_[x1[idx], np.ones(len(idx))]
    f2 = np.c_[x2[idx], np.ones(len(idx))] @ R
    parallax = np.degrees(np.arctan2(np.linalg.norm(np.cross(f1, f2), axis=1), np.sum(f1 * f2, axis=1)))
    med = float(np.median(parallax)) if len(idx) else 0.0
    reason = ""
    if inliers.sum() < config.min_inliers:
        reason = f"only {int(inliers.sum())} inliers (< min_inliers={config.min_inliers})"
    elif med < config.min_median_angle_deg:
        reason = (f"median parallax {med:.3g} deg < {config.min_median_angle_deg} deg: "
                  "baseline too small (pure rotation?), translation direction is not determined")
    elif in_front.sum() < 0.5 * inliers.sum():
        reason = "most inliers fail the cheirality test"
    return RelativePoseResult(
        success=reason == "", reason=reason, R=R, t=t, E=E, F=F, inlier_mask=inliers, n_inliers=int(inliers.sum()),
        in_front_mask=in_front, median_angle_deg=med, iterations=iterations, **extra,
    )


def estimate_relative_pose(uv1_px, uv2_px, K1, K2, *, config: TwoViewConfig | None = None) -> RelativePoseResult:
    """Calibrated relative pose: 5-point LO-MSAC, cheirality, LM refinement.

    Args:
        uv1_px: (N, 2) pixel coordinates in image 1 (our convention; undistorted
            pinhole pixels — unproject distorted cameras first).
        uv2_px: (N, 2) matching pixels in image 2.
        K1: (3, 3) intrinsics of camera 1 (cx, cy in our convention).
        K2: (3, 3) intrinsics of camera 2.
        config: `TwoViewConfig`.

    Returns:
        `RelativePoseResult` with ``cam2_from_cam1``.
    """
    config = config or TwoViewConfig()
    u1, u2 = _check_matches(uv1_px, uv2_px)
    K1 = np.asarray(K1, dtype=np.float64)
    K2 = np.asarray(K2, dtype=np.float64)
    check_shape(K1, [3, 3], "K1")
    check_shape(K2, [3, 3], "K2")
    n = len(u1)
    if n < 5:
        return _failure(n, f"need >= 5 matches, got {n}")
    x1, x2 = _to_norm(u1, K1), _to_norm(u2, K2)
    thr = config.ransac.threshold_px
    if config.backend == "opencv":
        f_mean = 0.25 * (K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1])
        def explained(E):  # our inliers of an essential matrix: Sampson distance in pixels
            return sampson_distance(fundamental_from_essential(E, K1, K2), u1, u2) < thr

        def opencv_essential(sel, method):  # the best of OpenCV's (possibly stacked) solutions, or None
            E, mask = cv2.findEssentialMat(x1[sel], x2[sel], np.eye(3), method=method, prob=config.ransac.confidence,
                                           threshold=thr / f_mean, maxIters=config.ransac.max_iterations)
            if E is None or mask is None or E.ndim != 2 or E.shape[1] != 3 or E.shape[0] % 3:
                return None
            cands = [(Ek, explained(Ek)) for Ek in (project_to_essential(E[k:k + 3]) for k in range(0, E.shape[0], 3))]
            best, best_inliers = max(cands, key=lambda c: int(c[1].sum()))
            return best, best_inliers, mask.ravel().astype(bool)

        usac = opencv_essential(np.arange(n), cv2.USAC_MAGSAC)
        if usac is None:
            return _failure(n, "OpenCV findEssentialMat found no model")
        E, inliers, consensus = usac
        if inliers.sum() < _USAC_MIN_EXPLAINED * consensus.sum() and consensus.sum() >= 5:
            # MAGSAC++'s final weighted fit can return a model far from the consensus set it reports: measured
            # on denoised photos (f = 1520 px, 1 px threshold) 58 points reported, 0 explained; on synthetic
            # pairs 0.5 % of draws (tests/mvgeo/test_twoview_usac.py). Fit that consensus set again.
            refit = opencv_essential(np.flatnonzero(consensus), cv2.RANSAC)
            if refit is not None and refit[1].sum() > inliers.sum():
                E, inliers, _ = refit
        return _resolve_planar(u1, u2, K1, K2, _finish(u1, u2, K1, K2, E, inliers, 0, config), config)

    h1, h2 = np.c_[u1, np.ones(n)], np.c_[u2, np.ones(n)]
    K1inv, K2invT = np.linalg.inv(K1), np.linalg.inv(K2).T

    def resid(E):
        return _sampson_h(K2invT @ E @ K1inv, h1, h2)

    res = ransac(
        n, 5,
        lambda s: essential_5point(x1[s], x2[s]),
        resid,
        config=config.ransac,
        fit_nonminimal=lambda idx: [essential_from_linear(x1[idx], x2[idx])] if len(idx) >= 8 else [],
    )
    if res.model is None or res.inlier_mask.sum() < 5:
        return _failure(n, "RANSAC found no model with >= 5 inliers", res.iterations)
    return _resolve_planar(u1, u2, K1, K2, _finish(u1, u2, K1, K2, res.model, res.inlier_mask, res.iterations,
                                                   config), config)


def _homography_inliers(u1: np.ndarray, u2: np.ndarray, thr: float) -> np.ndarray | None:
    """(N,) bool inliers of the best homography ``u2 ~ H u1`` (transfer error < `thr` px), or None."""
    if len(u1) < 4:
        return None
    # USAC_ACCURATE (local optimisation): on llff_like's ten focal pairs it found about as many or more
    # homography inliers than plain RANSAC with 2000 iterations, in 6 ms instead of 32 ms per pair. Plain
    # RANSAC where USAC asserts on degenerate sample sets.
    try:
        Hm, hmask = cv2.findHomography(u1, u2, cv2.USAC_ACCURATE, thr, maxIters=2000, confidence=0.999)
    except cv2.error:
        Hm, hmask = cv2.findHomography(u1, u2, cv2.RANSAC, thr, maxIters=2000, confidence=0.999)
    return None if Hm is None or hmask is None else hmask.ravel().astype(bool)


def homography_gric_margin(u1: np.ndarray, u2: np.ndarray, Hm: np.ndarray, sampson_px: np.ndarray) -> float:
    """Torr's GRIC of the essential model minus that of the homography `Hm` on the same matches (> 0: the
    homography is the better model: the points lie on a plane to within the noise).

    GRIC = sum_i min(e_i^2 / s^2, 2 (r - d)) + n d ln r + k ln(r n), with r = 4 (two image points), the
    manifold's dimension d (E: 3, H: 2) and parameters k (E: 5, H: 8), e_i the geometric error (the Sampson
    distance for E; half the symmetric transfer error's square for H, the squared geometric error to first
    order when both images carry the noise) and s the noise, estimated from the Sampson distances (1.4826
    times their median: one residual dimension). On a plane both models fit to the noise, and H's smaller
    dimension wins by about 0.39 n; relief whose parallax is above about 0.6 s rms tips it to E.

    Args:
        u1: (N, 2) pixels in image 1; u2: (N, 2) in image 2.
        Hm: (3, 3) homography ``u2 ~ Hm u1``.
        sampson_px: (N,) the essential model's Sampson distances in pixels.
    """
    n = len(u1)
    s2 = max(float(1.4826 * np.median(sampson_px)) ** 2, 1e-12)

    def transfer2(A, a, b):
        h = np.c_[a, np.ones(len(a))] @ A.T
        with np.errstate(divide="ignore", invalid="ignore"):
            d2 = np.sum((h[:, :2] / h[:, 2:] - b) ** 2, axis=1)
        return np.where(np.isfinite(d2), d2, np.inf)

    e2_h = 0.25 * (transfer2(Hm, u1, u2) + transfer2(np.linalg.inv(Hm), u2, u1))
    r = 4.0
    gric_h = np.minimum(e2_h / s2, 2 * (r - 2)).sum() + n * 2 * np.log(r) + 8 * np.log(r * n)
    gric_e = np.minimum(sampson_px**2 / s2, 2 * (r - 3)).sum() + n * 3 * np.log(r) + 5 * np.log(r * n)
    return float(gric_e - gric_h)


def _resolve_planar(u1, u2, K1, K2, out: RelativePoseResult, config: TwoViewConfig) -> RelativePoseResult:
    """A calibrated pair whose inliers a homography explains as well: choose between the plane's two poses.

    On a plane two relative poses explain the matches to the noise (the two physical decompositions of the
    homography), and the essential-matrix fit ends on either: on the planar scenes of
    `tests/mvgeo/_scenes.make_two_view` (0.3 px noise) 29 of 100 came back about 8 deg off as successes.
    Their Sampson residuals agree to the noise (refining the right pose's decomposition on them slid it to
    the wrong one on 2 of 24), but the wrong one tends to put some points behind a camera. Where the
    homography is the better model (`homography_gric_margin` > 0), the decomposition putting the most
    inliers in front of both cameras is taken, unrefined, when the essential fit is nearer the other one (as
    COLMAP takes it for pairs it classifies as planar); where the other puts at least
    ``config.planar_rival_front`` of that count in front, nothing tells them apart and the pair fails,
    naming the ambiguity.
    """
    if out.n_inliers < max(config.min_inliers, 8):
        return out
    thr = config.ransac.threshold_px
    # The models are compared on the matches within 5 thresholds of E, not on E's inliers: those are cut at
    # one threshold, which at a noise near it halves the noise they show (measured 0.5-0.7 px at 1 px), and
    # the comparison would then hold the noise against the two-dimensional model. Random matches rarely fall
    # that near an epipolar line, and GRIC caps their cost.
    sampson = sampson_distance(out.F, u1, u2)
    near = np.flatnonzero(sampson < 5.0 * thr)
    a, b = u1[near], u2[near]
    # The transfer error carries both images' noise in two dimensions: twice the Sampson threshold.
    hmask = _homography_inliers(a, b, 2.0 * thr)
    if hmask is None or hmask.sum() < 8:
        return out
    Hm = cv2.findHomography(a[hmask], b[hmask], 0)[0]  # least squares on the plane's inliers
    if Hm is None or not np.all(np.isfinite(Hm)) or abs(np.linalg.det(Hm)) < 1e-12:
        return out
    margin = homography_gric_margin(a, b, Hm, sampson[near])
    if margin <= 0:
        return out
    idx = np.flatnonzero(out.inlier_mask)
    x1, x2 = _to_norm(u1[idx], K1), _to_norm(u2[idx], K2)
    r1, r2 = np.c_[x1, np.ones(len(idx))], np.c_[x2, np.ones(len(idx))]
    poses: list[tuple[int, np.ndarray, np.ndarray]] = []  # (inliers in front, R, t): the best sign per rotation
    for R, t in zip(*cv2.decomposeHomographyMat(np.linalg.inv(K2) @ Hm @ K1, np.eye(3))[1:3], strict=True):
        t = t.ravel()
        if not (np.all(np.isfinite(R)) and np.isfinite(t).all()) or np.linalg.norm(t) < 1e-3:
            continue  # no translation (pure rotation, or the plane at infinity): the parallax test decides
        t = t / np.linalg.norm(t)
        tri = triangulate_two_view(r1, r2, np.c_[R, t], method="mid2", criteria=_CHEIRALITY)
        count = int((tri.in_front & tri.finite).sum())
        same = [k for k, p in enumerate(poses) if float(rotation_error_deg(R, p[1])) <= 1.0]
        if not same:
            poses.append((count, R, t))
        elif count > poses[same[0]][0]:
            poses[same[0]] = (count, R, t)
    if len(poses) < 2:
        return out
    poses.sort(key=lambda p: -p[0])
    (best_front, R, t), rival = poses[0], poses[1]
    if rival[0] >= config.planar_rival_front * best_front:
        return replace(out, success=False, reason=(
            f"a homography explains the inliers as well as E (planar scene; GRIC margin {margin:.0f}) and its two "
            f"poses, {float(rotation_error_deg(R, rival[1])):.1f} deg apart, put {best_front} and {rival[0]} of "
            f"the {len(idx)} inliers in front of both cameras: the relative pose is ambiguous"))
    if float(rotation_error_deg(out.R, R)) <= float(rotation_error_deg(out.R, rival[1])):
        return out
    E = essential_from_pose(R, t)
    return _finish(u1, u2, K1, K2, E / np.linalg.norm(E), out.inlier_mask, out.iterations,
                   replace(config, refine=False))


def estimate_fundamental(uv1_px, uv2_px, *, config: TwoViewConfig | None = None):
    """Fundamental matrix by 7-point LO-MSAC (or OpenCV USAC_MAGSAC), Sampson threshold in pixels.

    Args:
        uv1_px: (N, 2), N >= 8.
        uv2_px: (N, 2).
        config: `TwoViewConfig`.

    Returns:
        ``(F (3, 3) or None, inlier_mask (N,), iterations)``; F is refit on all
        inliers with the normalised 8-point algorithm.
    """
    config = config or TwoViewConfig()
    u1, u2 = _check_matches(uv1_px, uv2_px)
    n = len(u1)
    thr = config.ransac.threshold_px
    if n < 8:
        return None, np.zeros(n, bool), 0
    if config.backend == "opencv":
        F, mask = cv2.findFundamentalMat(u1, u2, cv2.USAC_MAGSAC, thr, config.ransac.confidence,
                                         config.ransac.max_iterations)
        if F is None or F.shape != (3, 3):
            return None, np.zeros(n, bool), 0
        F = F / np.linalg.norm(F)
        inliers = sampson_distance(F, u1, u2) < thr
        consensus = np.zeros(n, bool) if mask is None else mask.ravel().astype(bool)
        if inliers.sum() < _USAC_MIN_EXPLAINED * consensus.sum() and consensus.sum() >= 8:
            # As in `estimate_relative_pose`: USAC's model does not explain its own consensus set; refit it.
            F8 = fundamental_8point(u1[consensus], u2[consensus])
            F8 = F8 / np.linalg.norm(F8)
            inliers8 = sampson_distance(F8, u1, u2) < thr
            if inliers8.sum() > inliers.sum():
                F, inliers = F8, inliers8
        return F, inliers, 0
    h1, h2 = np.c_[u1, np.ones(n)], np.c_[u2, np.ones(n)]
    res = ransac(
        n, 7,
        lambda s: fundamental_7point(u1[s], u2[s]),
        lambda F: _sampson_h(F, h1, h2),
        config=config.ransac,
        fit_nonminimal=lambda idx: [fundamental_8point(u1[idx], u2[idx])] if len(idx) >= 8 else [],
    )
    if res.model is None:
        return None, res.inlier_mask, res.iterations
    F = res.model
    mask = res.inlier_mask
    if mask.sum() >= 8:
        F8 = fundamental_8point(u1[mask], u2[mask])
        if np.sum(np.minimum(sampson_distance(F8, u1, u2), thr) ** 2) <= np.sum(
            np.minimum(sampson_distance(F, u1, u2), thr) ** 2
        ):
            F = F8
    return F, sampson_distance(F, u1, u2) < thr, res.iterations


def _sampson_h(F: np.ndarray, h1: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """Sampson distance for homogeneous points (N, 3); the hot loop of RANSAC scoring (no checks)."""
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.abs(np.einsum("ij,ij->i", h2, Fx1))
    den2 = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return num / np.sqrt(np.where(den2 > 0, den2, 1.0))


def _K(f: float, c: tuple[float, float]) -> np.ndarray:
    return np.array([[f, 0.0, c[0]], [0.0, f, c[1]], [0.0, 0.0, 1.0]])


def focal_from_fundamental(F, image_size_wh, *, search_range: tuple[float, float] = (0.2, 5.0)) -> FocalEstimate:
    """Shared focal length (principal point at the image centre) by 1-D search.

    Minimises ``g(f) = (s1 - s2) / (s1 + s2)`` over the singular values of
    ``E(f) = K(f)^T F K(f)``: zero exactly at the true focal for noise-free F.

    Args:
        F: (3, 3) on our pixel coordinates.
        image_size_wh: ``(W, H)``; the principal point is ``(W/2, H/2)`` (our convention).
        search_range: interval as multiples of ``max(W, H)``.

    Returns:
        `FocalEstimate`.
    """
    F = np.asarray(F, dtype=np.float64)
    check_shape(F, [3, 3], "F")
    W, H = image_size_wh
    c = (W / 2.0, H / 2.0)
    scale = float(max(W, H))

    def cost(log_f: float) -> float:
        K = _K(np.exp(log_f), c)
        s = np.linalg.svd(K.T @ F @ K, compute_uv=False)
        return float((s[0] - s[1]) / max(s[0] + s[1], 1e-300))

    lo, hi = np.log(search_range[0] * scale), np.log(search_range[1] * scale)
    grid = np.linspace(lo, hi, 121)
    vals = np.array([cost(g) for g in grid])
    k = int(np.argmin(vals))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    opt = minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 1e-10})
    log_f = float(opt.x) if opt.fun <= vals[k] else float(grid[k])
    at_bound = bool(abs(log_f - lo) < 1e-6 or abs(log_f - hi) < 1e-6)
    return FocalEstimate(focal_px=float(np.exp(log_f)), cost=min(float(opt.fun), float(vals[k])), at_bound=at_bound)


def estimate_relative_pose_uncalibrated(
    uv1_px, uv2_px, image_size_wh, *, config: TwoViewConfig | None = None, seed: int | None = None
) -> RelativePoseResult:
    """Relative pose and a shared focal length from matches of one unknown pinhole camera.

    Assumes both images come from the same camera (same focal length),
    square pixels, principal point at the image centre, no distortion.

    Args:
        uv1_px: (N, 2) pixels in image 1 (our convention).
        uv2_px: (N, 2) matching pixels in image 2.
        image_size_wh: ``(W, H)`` of both images.
        config: `TwoViewConfig`.
        seed: overrides ``config.ransac.seed`` when given.

    Returns:
        `RelativePoseResult` with ``focal_px``, ``focal_rel_std``,
        ``focal_well_determined`` and ``homography_ratio`` filled in.
    """
    config = config or TwoViewConfig()
    if seed is not None:
        config = replace(config, ransac=replace(config.ransac, seed=int(seed)))
    u1, u2 = _check_matches(uv1_px, uv2_px)
    n = len(u1)
    W, H = image_size_wh
    c = (W / 2.0, H / 2.0)
    thr = config.ransac.threshold_px
    F, mask, iters = estimate_fundamental(u1, u2, config=config)
    if F is None or mask.sum() < 8:
        return _failure(n, "no fundamental matrix with >= 8 inliers", iters)
    hmask = _homography_inliers(u1, u2, thr)
    h_ratio = 0.0 if hmask is None else float(hmask.sum()) / float(mask.sum())
    focal = focal_from_fundamental(F, (W, H), search_range=config.focal_search_range)
    f0 = focal.focal_px
    K0 = _K(f0, c)
    E = project_to_essential(K0.T @ F @ K0)
    idx = np.flatnonzero(mask)
    x1, x2 = _to_norm(u1[idx], K0), _to_norm(u2[idx], K0)
    R, t, _, _ = pose_from_essential(E, x1, x2)
    f, rel_std = f0, np.inf
    if len(idx) >= 7:
        R, t, f, rel_std = _refine(u1[idx], u2[idx], None, None, R, t, config.noise_floor_px,
                                   log_f0=float(np.log(f0)), principal_px=c)
    K = _K(f, c)
    E = essential_from_pose(R, t)
    out = _finish(u1, u2, K, K, E / np.linalg.norm(E), sampson_distance(fundamental_from_essential(E, K, K), u1, u2)
                  < thr, iters, replace(config, refine=False),
                  extra=dict(focal_px=f, focal_rel_std=rel_std, focal_well_determined=bool(
                      rel_std <= config.max_focal_rel_std and not focal.at_bound), homography_ratio=h_ratio))
    # The homography test names the root cause, so it takes precedence over the symptoms it causes.
    if h_ratio >= config.max_homography_ratio:
        out = replace(out, success=False, reason=(
            f"a homography explains {h_ratio:.0%} of the F inliers (planar scene or pure rotation): "
            "F and the focal length are not determined"))
    return out

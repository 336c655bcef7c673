"""Pose-accuracy metrics (numpy float64): rotation / translation-direction
errors, relative-pose errors over all pairs (RRA/RTA style, as reported by
DUSt3R and InstantSplat), ATE after Sim(3) alignment, RPE, pose AUC, and the
one-call `compare_poses`.

Poses are ``cam_from_world`` ``(..., 3, 4)`` or ``(..., 4, 4)``
(docs/conventions.md). Angles come back in degrees (``_deg``); distances in
the *reference* poses' units.

Failures are explicit: a pose that is missing (not registered) counts as an
infinite error in accuracies and AUCs; an undefined direction (zero-length
translation) is ``nan`` in the per-pair arrays and is counted in
``PoseMetrics.n_pairs_undefined``, never silently dropped from a mean.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from mvgeo.common.errors import DegenerateGeometryError, ShapeError, check_shape
from mvgeo.transforms import Rt_from_matrix, Sim3, camera_centre, compose, invert, umeyama

__all__ = [
    "rotation_error_deg",
    "translation_direction_error_deg",
    "RelativePoseErrors",
    "relative_pose_errors",
    "AteResult",
    "ate",
    "RpeResult",
    "rpe",
    "pose_auc",
    "accuracy_at",
    "PoseMetrics",
    "compare_poses",
]

DEFAULT_THRESHOLDS_DEG = (5.0, 10.0, 20.0)


def rotation_error_deg(R_a, R_b) -> np.ndarray:
    """Angle of ``R_a^T R_b`` in degrees, in ``[0, 180]``.

    Uses ``atan2(|skew part|, (trace - 1) / 2)``, accurate at small angles
    (``arccos`` of the trace loses ~1e-8 rad near 0) and near 180.

    Args:
        R_a: (..., 3, 3) rotations.
        R_b: (..., 3, 3) rotations (batch dims broadcast).

    Returns:
        (...) float64 degrees.
    """
    R_a = np.asarray(R_a, dtype=np.float64)
    R_b = np.asarray(R_b, dtype=np.float64)
    check_shape(R_a, ["*", 3, 3], "R_a")
    check_shape(R_b, ["*", 3, 3], "R_b")
    M = np.swapaxes(R_a, -1, -2) @ R_b
    cos = (M[..., 0, 0] + M[..., 1, 1] + M[..., 2, 2] - 1) / 2
    s = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    sin = np.linalg.norm(s, axis=-1) / 2
    return np.degrees(np.arctan2(sin, cos))


def translation_direction_error_deg(t_a, t_b, *, eps: float = 1e-12) -> np.ndarray:
    """Angle between two translation vectors, degrees in ``[0, 180]``.

    Scale-free, so it compares poses known only up to scale. The sign matters
    (a translation estimated backwards is a 180 degree error).

    Args:
        t_a: (..., 3).
        t_b: (..., 3).
        eps: vectors shorter than this are "no direction".

    Returns:
        (...) float64 degrees; ``nan`` where either vector is shorter than
        ``eps`` (the direction is undefined; callers decide how to count it).
    """
    t_a = np.asarray(t_a, dtype=np.float64)
    t_b = np.asarray(t_b, dtype=np.float64)
    check_shape(t_a, ["*", 3], "t_a")
    check_shape(t_b, ["*", 3], "t_b")
    na = np.linalg.norm(t_a, axis=-1)
    nb = np.linalg.norm(t_b, axis=-1)
    cross = np.linalg.norm(np.cross(t_a, t_b), axis=-1)
    dot = np.sum(t_a * t_b, axis=-1)
    ang = np.degrees(np.arctan2(cross, dot))
    return np.where((na < eps) | (nb < eps), np.nan, ang)


@dataclass(frozen=True)
class RelativePoseErrors:
    """Errors of the relative poses ``cam_i_from_cam_j`` over all pairs ``i < j``.

    Attributes:
        pairs: (P, 2) int indices ``(i, j)``.
        rotation_deg: (P,) rotation error of ``R_i R_j^T``.
        translation_deg: (P,) direction error of the relative translation
            ``t_i - R_i R_j^T t_j`` (``nan`` where a baseline is zero).
    """

    pairs: np.ndarray
    rotation_deg: np.ndarray
    translation_deg: np.ndarray


def _as_poses(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[-1] != 4 or T.shape[-2] not in (3, 4):
        raise ShapeError(f"{name}: expected shape (N, 3, 4) or (N, 4, 4), got {T.shape}")
    return T


def relative_pose_errors(est_cam_from_world, ref_cam_from_world) -> RelativePoseErrors:
    """Relative rotation / translation-direction errors over all pairs (RRA/RTA inputs).

    Invariant to a similarity transform of either world, so no alignment is needed.

    Args:
        est_cam_from_world: (N, 3, 4) or (N, 4, 4).
        ref_cam_from_world: (N, 3, 4) or (N, 4, 4), same order.

    Returns:
        `RelativePoseErrors` with ``P = N (N - 1) / 2`` pairs.
    """
    est = _as_poses(est_cam_from_world, "est_cam_from_world")
    ref = _as_poses(ref_cam_from_world, "ref_cam_from_world")
    if est.shape[0] != ref.shape[0]:
        raise ShapeError(f"est and ref must hold the same number of poses, got {est.shape[0]} and {ref.shape[0]}")
    i, j = np.triu_indices(est.shape[0], k=1)
    rel_est = compose(est[i], invert(est[j]))
    rel_ref = compose(ref[i], invert(ref[j]))
    Re, te = Rt_from_matrix(rel_est)
    Rr, tr = Rt_from_matrix(rel_ref)
    # Baselines below 1e-9 of the scene's extent count as zero (undefined direction).
    eps_e = 1e-9 * max(float(np.max(np.abs(te), initial=0.0)), 1e-300)
    eps_r = 1e-9 * max(float(np.max(np.abs(tr), initial=0.0)), 1e-300)
    t_err = translation_direction_error_deg(te, tr, eps=0.0)
    t_err = np.where(np.linalg.norm(te, axis=-1) <= eps_e, np.nan, t_err)
    t_err = np.where(np.linalg.norm(tr, axis=-1) <= eps_r, np.nan, t_err)
    return RelativePoseErrors(
        pairs=np.stack([i, j], axis=-1), rotation_deg=rotation_error_deg(Re, Rr), translation_deg=t_err
    )


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error of camera centres after Sim(3) (or SE(3)) alignment.

    Attributes:
        rmse, mean, median, max: statistics of ``errors``, reference units.
        errors: (N,) per-camera centre distance after alignment.
        ref_from_est: the `Sim3` mapping estimated centres onto the reference.
        aligned_centres: (N, 3) estimated centres mapped into the reference frame.
    """

    rmse: float
    mean: float
    median: float
    max: float
    errors: np.ndarray
    ref_from_est: Sim3
    aligned_centres: np.ndarray


def ate(est_centres, ref_centres, *, with_scale: bool = True, weights=None) -> AteResult:
    """ATE: align estimated centres to the reference with Umeyama, then measure distances.

    Args:
        est_centres: (N, 3) camera centres in the estimate's world frame.
        ref_centres: (N, 3) matching reference centres.
        with_scale: Sim(3) (default; pose-free reconstructions have unknown
            scale) or SE(3).
        weights: (N,) optional Umeyama weights.

    Returns:
        `AteResult`.

    Raises:
        DegenerateGeometryError: fewer than 2 centres, or all estimated (or, with scale, reference) centres
            coincide.
    """
    est = np.asarray(est_centres, dtype=np.float64)
    ref = np.asarray(ref_centres, dtype=np.float64)
    check_shape(est, ["N", 3], "est_centres")
    check_shape(ref, [est.shape[0], 3], "ref_centres")
    spread = np.abs(ref - ref.mean(axis=0)).max(initial=0.0)
    if with_scale and spread <= 1e-12 * max(float(np.abs(ref).max(initial=0.0)), 1e-300):
        # Umeyama's scale would be 0 (every estimate collapsed onto the one point, an ATE of 0): no Sim(3)
        # relates a spread of centres to a single one (a camera turning about its centre).
        raise DegenerateGeometryError("ate: all reference centres coincide; the Sim(3) scale is undetermined")
    sim = umeyama(est, ref, weights=weights, with_scale=with_scale)
    aligned = sim.apply(est)
    err = np.linalg.norm(aligned - ref, axis=-1)
    return AteResult(
        rmse=float(np.sqrt(np.mean(err**2))),
        mean=float(err.mean()),
        median=float(np.median(err)),
        max=float(err.max()),
        errors=err,
        ref_from_est=sim,
        aligned_centres=aligned,
    )


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error between frames ``k`` and ``k + delta`` (TUM RGB-D definition).

    Attributes:
        translation_rmse: RMSE of the translation error, reference units.
        rotation_rmse_deg: RMSE of the rotation error, degrees.
        translation_errors: (M,) per-pair translation error.
        rotation_errors_deg: (M,) per-pair rotation error.
    """

    translation_rmse: float
    rotation_rmse_deg: float
    translation_errors: np.ndarray
    rotation_errors_deg: np.ndarray


def rpe(est_cam_from_world, ref_cam_from_world, *, delta: int = 1, scale: float = 1.0) -> RpeResult:
    """Relative pose error for consecutive frames (in the given order).

    For each ``k``, compares the relative motions ``cam_k_from_cam_{k+delta}``;
    the estimate's translations are multiplied by ``scale`` first (use
    ``ate(...).ref_from_est.scale`` for a pose-free estimate).

    Args:
        est_cam_from_world: (N, 3, 4) or (N, 4, 4).
        ref_cam_from_world: same shape, same order.
        delta: frame offset, ``1 <= delta < N``.
        scale: estimate-to-reference scale factor.

    Returns:
        `RpeResult`.
    """
    est = _as_poses(est_cam_from_world, "est_cam_from_world")
    ref = _as_poses(ref_cam_from_world, "ref_cam_from_world")
    n = est.shape[0]
    if ref.shape[0] != n:
        raise ShapeError(f"est and ref must hold the same number of poses, got {n} and {ref.shape[0]}")
    if not 1 <= delta < n:
        raise DegenerateGeometryError(f"rpe: need 1 <= delta < N, got delta={delta}, N={n}")
    est = est.copy()
    est[:, :3, 3] *= scale
    k = np.arange(n - delta)
    rel_e = compose(est[k], invert(est[k + delta]))
    rel_r = compose(ref[k], invert(ref[k + delta]))
    err = compose(invert(rel_r), rel_e)
    R, t = Rt_from_matrix(err)
    t_err = np.linalg.norm(t, axis=-1)
    r_err = rotation_error_deg(R, np.eye(3))
    return RpeResult(
        translation_rmse=float(np.sqrt(np.mean(t_err**2))),
        rotation_rmse_deg=float(np.sqrt(np.mean(r_err**2))),
        translation_errors=t_err,
        rotation_errors_deg=r_err,
    )


def pose_auc(errors_deg, thresholds: Sequence[float] = DEFAULT_THRESHOLDS_DEG) -> dict[float, float]:
    """Area under the recall-vs-error curve up to each threshold, normalised to [0, 1].

    The exact integral of the empirical recall ``r(e) = #{errors <= e} / n``
    from 0 to the threshold, divided by the threshold (the SuperGlue/LoFTR
    definition, piecewise-linear between sorted errors). ``nan`` and ``inf``
    errors (failed/unregistered) count as failures: they are in ``n`` but never
    recalled.

    Args:
        errors_deg: (M,) errors in degrees, M >= 1.
        thresholds: positive thresholds in degrees.

    Returns:
        ``{threshold: auc}``.
    """
    e = np.asarray(errors_deg, dtype=np.float64).ravel()
    if e.size == 0:
        raise DegenerateGeometryError("pose_auc: no errors given")
    n = e.size
    e = np.where(np.isfinite(e), e, np.inf)
    e = np.sort(e)
    out: dict[float, float] = {}
    for thr in thresholds:
        if not thr > 0:
            raise DegenerateGeometryError(f"pose_auc: thresholds must be positive, got {thr}")
        finite = e[e < thr]
        x = np.concatenate([[0.0], finite, [thr]])
        recall = np.concatenate([[0.0], np.arange(1, finite.size + 1) / n])
        recall = np.concatenate([recall, recall[-1:]])
        # Piecewise-linear recall between consecutive sorted errors (trapezoid rule).
        out[float(thr)] = float(np.trapezoid(recall, x) / thr)
    return out


def accuracy_at(errors_deg, thresholds: Sequence[float] = DEFAULT_THRESHOLDS_DEG) -> dict[float, float]:
    """Fraction of errors ``< threshold`` for each threshold (``nan``/``inf`` count as failures)."""
    e = np.asarray(errors_deg, dtype=np.float64).ravel()
    if e.size == 0:
        raise DegenerateGeometryError("accuracy_at: no errors given")
    e = np.where(np.isfinite(e), e, np.inf)
    return {float(t): float(np.mean(e < t)) for t in thresholds}


@dataclass(frozen=True)
class PoseMetrics:
    """Everything `compare_poses` measures.

    Attributes:
        n_ref: number of reference images.
        n_registered: reference names present in the estimate.
        registered_fraction: ``n_registered / n_ref``.
        names: the matched names, in reference order.
        rotation_deg: (P,) relative rotation errors over matched pairs.
        translation_deg: (P,) relative translation-direction errors over
            matched pairs (``nan`` where a baseline is zero).
        n_pairs_total: pairs of reference images, ``n_ref (n_ref - 1) / 2``.
        n_pairs_undefined: matched pairs with a zero reference or estimated
            baseline (direction undefined); they count as failures below.
        rra: ``{thr: fraction}`` relative rotation accuracy over *all*
            reference pairs (unregistered pairs fail).
        rta: same for translation direction.
        auc: ``{thr: AUC}`` of ``max(rotation, translation)`` error over all
            reference pairs (unregistered pairs fail), the DUSt3R/InstantSplat
            "mAA"-style summary.
        median_rotation_deg, median_translation_deg: medians over matched pairs
            (undefined pairs excluded from the translation median); ``nan`` when
            fewer than 2 images are matched.
        ate: `AteResult` after Sim(3) alignment of camera centres, or None when
            fewer than 3 images are matched or all estimated centres coincide
            (the alignment is not determined).
    """

    n_ref: int
    n_registered: int
    registered_fraction: float
    names: list[str]
    rotation_deg: np.ndarray
    translation_deg: np.ndarray
    n_pairs_total: int
    n_pairs_undefined: int
    rra: dict[float, float]
    rta: dict[float, float]
    auc: dict[float, float]
    median_rotation_deg: float
    median_translation_deg: float
    ate: AteResult | None = field(default=None)

    def summary(self) -> dict[str, float]:
        """Flat scalar dict for reports (keys like ``rra@5``, ``ate_rmse``)."""
        out = {
            "registered_fraction": self.registered_fraction,
            "median_rotation_deg": self.median_rotation_deg,
            "median_translation_deg": self.median_translation_deg,
        }
        for name, d in (("rra", self.rra), ("rta", self.rta), ("auc", self.auc)):
            out.update({f"{name}@{thr:g}": v for thr, v in d.items()})
        out["ate_rmse"] = self.ate.rmse if self.ate is not None else float("nan")
        return out


def compare_poses(
    est: Mapping[str, np.ndarray],
    ref: Mapping[str, np.ndarray],
    *,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS_DEG,
) -> PoseMetrics:
    """Compare estimated to reference poses matched by image name.

    Args:
        est: ``{name: cam_from_world (3, 4) or (4, 4)}`` (any world frame and scale).
        ref: ``{name: cam_from_world}`` reference poses. Names in ``est`` that
            are not in ``ref`` are ignored.
        thresholds: degrees, for RRA/RTA/AUC.

    Returns:
        `PoseMetrics`.

    Raises:
        DegenerateGeometryError: ``ref`` holds fewer than 2 images.
    """
    names_ref = list(ref.keys())
    n_ref = len(names_ref)
    if n_ref < 2:
        raise DegenerateGeometryError("compare_poses: need at least 2 reference images")
    names = [n for n in names_ref if n in est]
    n_reg = len(names)
    n_pairs_total = n_ref * (n_ref - 1) // 2
    if n_reg >= 2:
        E = np.stack([np.asarray(est[n], dtype=np.float64)[:3] for n in names])
        Rf = np.stack([np.asarray(ref[n], dtype=np.float64)[:3] for n in names])
        rel = relative_pose_errors(E, Rf)
        rot, tra = rel.rotation_deg, rel.translation_deg
    else:
        rot = tra = np.zeros(0)
    n_undef = int(np.count_nonzero(np.isnan(tra)))
    n_missing = n_pairs_total - rot.size
    fail = np.full(n_missing, np.inf)
    rot_all = np.concatenate([rot, fail])
    tra_all = np.concatenate([np.where(np.isnan(tra), np.inf, tra), fail])
    max_all = np.maximum(rot_all, tra_all)
    ate_res = None
    if n_reg >= 3:
        try:
            ate_res = ate(camera_centre(E), camera_centre(Rf))
        except DegenerateGeometryError:
            ate_res = None
    finite_t = tra[np.isfinite(tra)]
    return PoseMetrics(
        n_ref=n_ref,
        n_registered=n_reg,
        registered_fraction=n_reg / n_ref,
        names=names,
        rotation_deg=rot,
        translation_deg=tra,
        n_pairs_total=n_pairs_total,
        n_pairs_undefined=n_undef,
        rra=accuracy_at(rot_all, thresholds),
        rta=accuracy_at(tra_all, thresholds),
        auc=pose_auc(max_all, thresholds),
        median_rotation_deg=float(np.median(rot)) if rot.size else float("nan"),
        median_translation_deg=float(np.median(finite_t)) if finite_t.size else float("nan"),
        ate=ate_res,
    )

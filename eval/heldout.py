"""Held-out cameras for pose-free methods, as InstantSplat evaluates them.

A pose-free reconstruction lives in its own world frame and scale. To render
a held-out view we register the estimated *training* cameras to their ground
truth with a Sim(3) (Umeyama on camera centres), map the ground-truth
held-out cameras into the estimated frame with it, and (in the evaluation,
with `splat.fit_pose`) refine each held-out pose photometrically with the
Gaussians frozen.

Mapping a camera: with `est_from_ref = (s, R, t)` (`x_est = s R x_ref + t`)
and a reference camera `x_cam = R_c x_ref + t_c` (reference units), the same
camera in the estimated world, with its frame scaled to estimated units, is
`cam_from_world_est = [R_c R^T | s t_c - R_c R^T t]`. It sees every point
at the same pixel (projection is scale-invariant).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mvgeo.common.errors import DegenerateGeometryError, InputError
from mvgeo.transforms import Sim3, average_rotations_chordal, umeyama

__all__ = ["HeldoutMapping", "map_cameras", "map_cameras_local", "register_sim3"]


@dataclass(frozen=True)
class HeldoutMapping:
    """Result of `register_sim3` + `map_cameras`.

    Attributes:
        est_from_ref: Sim(3) mapping reference world points into the estimated world.
        cam_from_world: held-out name -> (3, 4) camera in the estimated world.
        registration_rmse: RMS residual of the training camera centres after
            registration, in reference units (the ATE of the fit).
        used_orientations: True when the centres were (nearly) collinear and
            the rotation came from the cameras' orientations instead.
    """

    est_from_ref: Sim3
    cam_from_world: dict[str, np.ndarray]
    registration_rmse: float
    used_orientations: bool


def _centre(cfw: np.ndarray) -> np.ndarray:
    return -cfw[:3, :3].T @ cfw[:3, 3]


#: `register_sim3` takes the rotation from the cameras' orientations when the reference centres' second
#: principal extent is under this fraction of the first (nearly collinear: a line of cameras).
COLLINEAR_RATIO = 0.1


def register_sim3(est: Mapping[str, np.ndarray], ref: Mapping[str, np.ndarray]) -> tuple[Sim3, bool]:
    """Sim(3) `est_from_ref` from cameras present in both (matched by name).

    Umeyama on the camera centres; when the centres are collinear or nearly so (`COLLINEAR_RATIO`: the
    rotation about the line is undetermined, or set by noise) the rotation is the chordal mean of the
    per-camera `R_est^T R_ref`, and scale and translation are refit with it.

    Returns:
        (est_from_ref, used_orientations).

    Raises:
        DegenerateGeometryError: fewer than 2 common cameras, or coincident centres.
    """
    names = [n for n in ref if n in est]
    if len(names) < 2:
        raise DegenerateGeometryError(f"Sim(3) registration needs >= 2 common cameras, got {len(names)}")
    E = {n: np.asarray(est[n], np.float64)[:3] for n in names}
    F = {n: np.asarray(ref[n], np.float64)[:3] for n in names}
    c_est = np.stack([_centre(E[n]) for n in names])
    c_ref = np.stack([_centre(F[n]) for n in names])
    spread_ref = np.linalg.norm(c_ref - c_ref.mean(0), axis=1).max()
    spread_est = np.linalg.norm(c_est - c_est.mean(0), axis=1).max()
    if spread_ref <= 1e-12 or spread_est <= 1e-12:
        raise DegenerateGeometryError("camera centres coincide: the Sim(3) scale is undetermined")
    sim = umeyama(c_ref, c_est, with_scale=True) if len(names) >= 3 else None
    # The centres fix the roll about their line only as well as they leave it: with the second principal
    # extent under `COLLINEAR_RATIO` of the first, noise of a thousandth of the line's length turned Umeyama's
    # rotation by 5-26 deg, where the cameras' orientations give it to their own error (a tenth of a degree).
    ext = np.linalg.svd(c_ref - c_ref.mean(0), compute_uv=False)
    if sim is not None and sim.well_posed and ext[1] >= COLLINEAR_RATIO * ext[0]:
        return sim, False
    # x_cam = R_ref x_ref + .. = R_est x_est + ..  with x_est = s R x_ref + t  =>  R_ref = R_est R.
    R = average_rotations_chordal(np.stack([E[n][:, :3].T @ F[n][:, :3] for n in names]))
    a = c_ref @ R.T - (c_ref @ R.T).mean(0)
    b = c_est - c_est.mean(0)
    s = float((a * b).sum() / (a * a).sum())
    if not s > 0:
        raise DegenerateGeometryError("registered scale is not positive (estimated trajectory reversed?)")
    t = c_est.mean(0) - s * (c_ref.mean(0) @ R.T)
    rmse = float(np.sqrt(np.mean(np.sum((s * c_ref @ R.T + t - c_est) ** 2, axis=1))))
    return Sim3(scale=s, R=R, t=t, rmse=rmse, well_posed=True), True


def map_cameras(est_train: Mapping[str, np.ndarray], ref_train: Mapping[str, np.ndarray],
                ref_heldout: Mapping[str, np.ndarray]) -> HeldoutMapping:
    """Map reference held-out cameras into the estimated world of a pose-free reconstruction.

    Args:
        est_train: name -> (3, 4)/(4, 4) estimated training `cam_from_world`.
        ref_train: name -> reference training `cam_from_world` (same names).
        ref_heldout: name -> reference held-out `cam_from_world`.

    Returns:
        `HeldoutMapping`.

    Raises:
        InputError: a held-out name is also a training name.
        DegenerateGeometryError: see `register_sim3`.
    """
    overlap = sorted(set(ref_heldout) & set(ref_train))
    if overlap:
        raise InputError(f"views {overlap} are both training and held-out")
    sim, used_orient = register_sim3(est_train, ref_train)
    names = [n for n in ref_train if n in est_train]
    c_est = np.stack([_centre(np.asarray(est_train[n], np.float64)[:3]) for n in names])
    c_ref = np.stack([_centre(np.asarray(ref_train[n], np.float64)[:3]) for n in names])
    # Residual in reference units: map the estimated centres back.
    back = ((c_est - sim.t) @ sim.R) / sim.scale
    rmse_ref = float(np.sqrt(np.mean(np.sum((back - c_ref) ** 2, axis=1))))
    out = {}
    for name, cfw in ref_heldout.items():
        m = np.asarray(cfw, np.float64)[:3]
        Rc, tc = m[:, :3], m[:, 3]
        R_new = Rc @ sim.R.T
        out[name] = np.hstack([R_new, (sim.scale * tc - R_new @ sim.t)[:, None]])
    return HeldoutMapping(sim, out, rmse_ref, used_orient)


def map_cameras_local(est_train: Mapping[str, np.ndarray], ref_train: Mapping[str, np.ndarray],
                      ref_heldout: Mapping[str, np.ndarray]) -> HeldoutMapping:
    """Map held-out cameras through their nearest training camera (robust to global distortion).

    A pose-free reconstruction with a wrong focal length is a *distorted* copy of the scene: no
    single Sim(3) fits all its cameras (measured on llff_like at 160x120: a 54% focal error, the
    globally mapped held-out cameras rendered at 8 dB, below the noisy photos). Locally it is
    consistent, so each held-out camera is placed relative to the training camera nearest to it
    (reference centres): ``cam_from_world_est = heldout_from_near (translation x s) @
    near_from_world_est``, with the scale ``s`` of the global Sim(3). The photometric refinement
    then starts close. `est_from_ref` and the RMSE are the global fit's (for reporting).

    Args / Returns / Raises: as `map_cameras`.
    """
    overlap = sorted(set(ref_heldout) & set(ref_train))
    if overlap:
        raise InputError(f"views {overlap} are both training and held-out")
    glob = map_cameras(est_train, ref_train, {})
    s = glob.est_from_ref.scale
    names = [n for n in ref_train if n in est_train]

    def h(m: np.ndarray) -> np.ndarray:
        out = np.eye(4)
        out[:3] = np.asarray(m, np.float64)[:3]
        return out

    out = {}
    for name, cfw in ref_heldout.items():
        c = _centre(np.asarray(cfw, np.float64)[:3])
        near = min(names, key=lambda n: float(np.linalg.norm(_centre(np.asarray(ref_train[n], np.float64)[:3]) - c)))
        rel = h(cfw) @ np.linalg.inv(h(ref_train[near]))
        rel[:3, 3] *= s
        out[name] = (rel @ h(est_train[near]))[:3]
    return HeldoutMapping(glob.est_from_ref, out, glob.registration_rmse, glob.used_orientations)

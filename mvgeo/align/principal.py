"""The principal point, where the views determine it.

Without a calibration the alignment, like COLMAP's mappers by default, puts the principal point at the image
centre. A real camera's is a few pixels to a few tens of pixels off, and on views that surround the object
that offset is not absorbed: every camera looks off by the same small angle (offset / focal), the ring closes
with it, and the rotations come out bent. Measured on the Middlebury temple ring (principal point 17 and 7 px
off the centre of 640x480, focal 1520 px): 1.00 deg median rotation error with the centre, 0.32 deg with the
principal point estimated here (docs/bench/principal_point.md).

On close views the principal point trades off against the rotations and the data hardly prefer one value
(DTU scan24 with sigma 25/255 noise: a standard deviation of 13-19 px, estimates 19-38 px from the truth that
doubled the rotation error where kept). So it is estimated once the solution is accepted, by one Gauss-Newton
step of the bundle adjustment with the principal point free (one for all views), and kept only where the data
determine it (`determined`): its standard deviation is below `MAX_STD_DEG` of view angle and its offset from
the centre is significant (chi-square of the offset over its standard deviations above `MIN_CHI2`, two
degrees of freedom at 99 %). The accepted solution is then adjusted and judged again with that principal
point (as a known principal point is, `mvgeo.align.solve.ideal_matches`, the focal still free); it is kept if
the verdict accepts it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from mvgeo.align.bundle_lm import LMProblem, principal_step
from mvgeo.align.inputs import AlignInputs
from mvgeo.align.solve import Candidate, adjust_and_judge
from mvgeo.align.stats import PrincipalPointStats
from mvgeo.common.timing import StageTimer

__all__ = ["MAX_STD_DEG", "MIN_CHI2", "PrincipalEstimate", "determined", "estimate_principal",
           "with_principal_point"]

#: The principal point's standard deviation, as an angle (std / focal), must be below this (deg). Measured
#: (docs/bench/principal_point.md): the temple ring 0.12-0.14 deg, llff_like 0.13; DTU scan24 clean 0.41-0.44
#: deg, with noise 0.98-1.17 deg.
MAX_STD_DEG = 0.25
#: Chi-square of the offset from the centre (two degrees of freedom) above which it is significant: 99 %.
MIN_CHI2 = 9.21


@dataclass(frozen=True)
class PrincipalEstimate:
    """The bundle adjustment's principal point for a solution (alignment pixels).

    Attributes:
        principal_px: (2,) the estimate; offset_px: (2,) from the image centre; std_px: (2,) its standard
            deviation; focal_px: the focal adjusted with it.
        determined: whether the views determine it (`determined`); why: the figures that decided.
    """

    principal_px: np.ndarray
    offset_px: np.ndarray
    std_px: np.ndarray
    focal_px: float
    determined: bool
    why: str


def determined(offset_px: np.ndarray, std_px: np.ndarray, focal_px: float) -> tuple[bool, str]:
    """Whether a principal point estimate is determined (see the module docstring), and why (figures)."""
    std_deg = math.degrees(float(np.max(std_px)) / focal_px)
    chi2 = float(np.sum((np.asarray(offset_px) / np.maximum(std_px, 1e-12)) ** 2))
    ok = std_deg < MAX_STD_DEG and chi2 > MIN_CHI2
    why = (f"standard deviation {std_deg:.2f} deg of view angle ({'<' if std_deg < MAX_STD_DEG else '>='} "
           f"{MAX_STD_DEG}), offset chi-square {chi2:.1f} ({'>' if chi2 > MIN_CHI2 else '<='} {MIN_CHI2})")
    return ok, why


def estimate_principal(c: Candidate, config) -> PrincipalEstimate | None:
    """The principal point `c`'s adjusted tracks imply: one Gauss-Newton step from `c`'s bundle adjustment
    (poses, focal, points) with the principal point free (`bundle_lm.principal_step`), or None where it does
    not apply (no bundle adjustment, or the calibration is known). `config`: `AlignConfig`."""
    b = c.ba
    if b is None or c.inputs.K_align is not None or b.track_xyz is None or b.obs_view is None or len(b.obs_view) == 0:
        return None
    Wa, Ha = c.inputs.align_wh
    n = len(b.cam_from_world)
    shared = bool(np.allclose(b.focal_px, b.focal_px[0]))
    f_index = np.zeros(n, np.int64) if shared else np.arange(n)
    logf = np.log(np.asarray(b.focal_px[:1] if shared else b.focal_px, np.float64))
    centre = np.array([Wa / 2.0, Ha / 2.0])
    pb = LMProblem(b.obs_view, b.obs_point, b.obs_uv, f_index, centre, True, True)
    principal, std = principal_step(b.cam_from_world[:, :, :3], b.cam_from_world[:, :, 3], logf,
                                    np.asarray(b.track_xyz, np.float64), pb, config.bundle.huber_px)
    f = float(np.median(b.focal_px))
    offset = principal - centre
    ok, why = determined(offset, std, f)
    return PrincipalEstimate(principal, offset, std, f, ok, why)


def _with_principal(inputs: AlignInputs, est: PrincipalEstimate) -> AlignInputs:
    """`inputs` with the estimated principal point as their K_align (square pixels; the focal stays free: no
    `intrinsics`)."""
    K = np.array([[est.focal_px, 0.0, est.principal_px[0]], [0.0, est.focal_px, est.principal_px[1]],
                  [0.0, 0.0, 1.0]])
    return replace(inputs, K_align=np.repeat(K[None], len(inputs), axis=0))


def with_principal_point(c: Candidate, config, timer: StageTimer) -> tuple[Candidate, PrincipalPointStats | None]:
    """The accepted solution `c` adjusted and judged again with the principal point its views determine, and
    the record (`AlignStats.principal_point`); `c` itself where it is refused, the principal point is not
    determined, or the verdict refuses the solution with it. `config`: `AlignConfig`."""
    if config.principal_point != "auto" or not c.verdict.ok:
        return c, None
    with timer.stage("bundle_adjust"):
        est = estimate_principal(c, config)
    if est is None:
        return c, None
    W0, H0 = c.inputs.input_wh
    Wa, Ha = c.inputs.align_wh
    scale = np.array([W0 / Wa, H0 / Ha])

    def record(kept: bool, why: str) -> PrincipalPointStats:
        return PrincipalPointStats([round(float(v), 2) for v in est.offset_px * scale],
                                   [round(float(v), 2) for v in est.std_px * scale], kept, why)

    if not est.determined:
        return c, record(False, "not determined: " + est.why)
    s = c.graph.grid_to_align
    start = replace(c.result, focal_px=np.full(len(c.inputs), est.focal_px / s))  # its poses: the adjustment's
    new = adjust_and_judge(c.graph, c.start, start, c.align_config, config, timer,
                           inputs=_with_principal(c.inputs, est), pairs=c.pairs, dropped=c.dropped,
                           unregistered=c.unregistered[len(c.graph.unregistered):], relocated=c.relocated)
    if not new.verdict.ok:
        return c, record(False, "determined (" + est.why + "), but the solution with it is refused: "
                         + "; ".join(r.message for r in new.verdict.reasons))
    return (replace(new, start_values=c.start_values, start_made_by=c.start_made_by),
            record(True, "determined: " + est.why))

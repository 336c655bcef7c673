"""A small, seeded LO-MSAC loop shared by the two-view and PnP estimators.

MSAC scoring (truncated squared residual, Torr & Zisserman 2000), adaptive
termination from the best inlier ratio at the requested confidence, and a
simple local optimisation (Chum, Matas & Kittler 2003): whenever a new best
model appears, refit it on its inliers with the non-minimal solver, a few
times, keeping each refit that improves the score.

The loop holds no state between calls; randomness comes only from
``numpy.random.default_rng(config.seed)`` (docs/conventions.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["RansacConfig", "RansacResult", "ransac", "required_iterations"]

@dataclass(frozen=True)
class RansacConfig:
    """Options of the robust estimators.

    Attributes:
        threshold_px: inlier threshold on the residual (pixels: Sampson
            distance for E/F, reprojection error for PnP).
        confidence: probability of drawing at least one all-inlier sample,
            used for adaptive termination.
        max_iterations: hard cap on samples.
        min_iterations: samples drawn even if the termination rule says stop
            earlier (guards against a lucky early sample hiding a better model).
        lo_iterations: local-optimisation refits per new best model (0 disables LO).
        seed: seed of the random generator; same seed and inputs give the same result.
    """

    threshold_px: float = 1.0
    confidence: float = 0.9999
    max_iterations: int = 10000
    min_iterations: int = 50
    lo_iterations: int = 5
    seed: int = 0


@dataclass(frozen=True)
class RansacResult[M]:
    """Outcome of `ransac`.

    Attributes:
        model: best model, or None if no sample produced one.
        inlier_mask: (N,) bool, residual < threshold for ``model``.
        score: MSAC cost of ``model`` (lower is better); ``inf`` when none.
        iterations: samples drawn.
    """

    model: M | None
    inlier_mask: np.ndarray
    score: float
    iterations: int


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> int:
    """Samples needed to draw one all-inlier sample with ``confidence`` (inf -> a large int)."""
    w = inlier_ratio**sample_size
    if w <= 0:
        return 2**31 - 1
    if w >= 1:
        return 1
    return int(math.ceil(math.log(1 - confidence) / math.log(1 - w)))


def ransac[M](
    n: int,
    sample_size: int,
    fit_minimal: Callable[[np.ndarray], Sequence[M]],
    residuals: Callable[[M], np.ndarray],
    *,
    config: RansacConfig,
    fit_nonminimal: Callable[[np.ndarray], Sequence[M]] | None = None,
) -> RansacResult[M]:
    """Seeded LO-MSAC.

    Args:
        n: number of data points.
        sample_size: minimal sample size.
        fit_minimal: sample indices (sample_size,) -> candidate models (possibly none).
        residuals: model -> (n,) non-negative residuals (``inf`` allowed).
        config: `RansacConfig`.
        fit_nonminimal: inlier indices (k,) -> candidate models, for LO.

    Returns:
        `RansacResult`.
    """
    rng = np.random.default_rng(config.seed)
    thr2 = config.threshold_px**2
    best: M | None = None
    best_score = math.inf
    best_mask = np.zeros(n, bool)
    if n < sample_size:
        return RansacResult(None, best_mask, best_score, 0)

    def score_of(model: M) -> tuple[float, np.ndarray]:
        r = np.asarray(residuals(model), dtype=np.float64)
        r2 = np.where(np.isfinite(r), r * r, np.inf)
        return float(np.sum(np.minimum(r2, thr2))), r2 < thr2

    needed = config.max_iterations
    it = 0
    while it < min(needed, config.max_iterations) or it < min(config.min_iterations, config.max_iterations):
        it += 1
        sample = rng.choice(n, size=sample_size, replace=False)
        for model in fit_minimal(sample):
            s, mask = score_of(model)
            if s >= best_score:
                continue
            best, best_score, best_mask = model, s, mask
            if fit_nonminimal is not None:
                for _ in range(config.lo_iterations):
                    if best_mask.sum() <= sample_size:
                        break
                    improved = False
                    for m2 in fit_nonminimal(np.flatnonzero(best_mask)):
                        s2, mask2 = score_of(m2)
                        if s2 < best_score:
                            best, best_score, best_mask, improved = m2, s2, mask2, True
                    if not improved:
                        break
            needed = required_iterations(best_mask.mean(), sample_size, config.confidence)
    return RansacResult(best, best_mask, best_score, it)

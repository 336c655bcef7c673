"""Small, seeded k-means (Lloyd) with k-means++ initialisation and restarts.

Written here because scikit-learn is not a dependency; the problem sizes are
tiny (a few dozen views, 6-D features). Tested against brute force on small
cases.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvgeo.common.errors import ShapeError


@dataclass(frozen=True)
class KMeansResult:
    """Attributes:
    labels: ``(N,)`` int cluster of each point, clusters numbered ``0..k-1`` by first appearance.
    centres: ``(k, D)`` float64.
    inertia: sum of squared distances of points to their centre.
    """

    labels: np.ndarray
    centres: np.ndarray
    inertia: float


def kmeans_pp_init(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding (Arthur & Vassilvitskii 2007): ``(k, D)`` centres chosen among the points.

    When all remaining squared distances are zero (fewer distinct points than
    `k`), the next centre is a uniformly random point.
    """
    n = x.shape[0]
    centres = [x[rng.integers(n)]]
    d2 = np.sum((x - centres[0]) ** 2, axis=1)
    for _ in range(1, k):
        total = d2.sum()
        i = rng.integers(n) if total <= 0 else rng.choice(n, p=d2 / total)
        centres.append(x[i])
        d2 = np.minimum(d2, np.sum((x - x[i]) ** 2, axis=1))
    return np.array(centres)


def _lloyd(x: np.ndarray, centres: np.ndarray, max_iter: int) -> tuple[np.ndarray, np.ndarray]:
    k = centres.shape[0]
    labels = np.full(x.shape[0], -1)
    for _ in range(max_iter):
        d2 = np.sum((x[:, None, :] - centres[None, :, :]) ** 2, axis=2)
        new = np.argmin(d2, axis=1)
        # An empty cluster takes the point farthest from its centre among clusters with > 1 member
        # (always possible since k <= N; handles duplicate points).
        for j in range(k):
            if not np.any(new == j):
                counts = np.bincount(new, minlength=k)
                cost = np.where(counts[new] > 1, d2[np.arange(len(x)), new], -1.0)
                new[int(np.argmax(cost))] = j
        if np.array_equal(new, labels):
            break
        labels = new
        centres = np.array([x[labels == j].mean(axis=0) for j in range(k)])
    return labels, centres


def _renumber(labels: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = list(dict.fromkeys(labels.tolist()))
    remap = {old: new for new, old in enumerate(order)}
    return np.array([remap[v] for v in labels]), centres[order]


def kmeans(x: np.ndarray, k: int, *, seed: int = 0, restarts: int = 8, max_iter: int = 100) -> KMeansResult:
    """Cluster the rows of `x` into `k` groups; the best of `restarts` seeded runs (lowest inertia).

    Args:
        x: ``(N, D)`` float.
        k: ``1 <= k <= N`` clusters (every cluster is non-empty).
        seed: seeds all restarts (one generator, consumed in order).
        restarts: independent k-means++ initialisations.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ShapeError(f"x: expected (N, D), got {x.shape}")
    n = x.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"k must be in [1, N={n}], got {k}")
    rng = np.random.default_rng(seed)
    best: KMeansResult | None = None
    for _ in range(max(1, restarts)):
        labels, centres = _lloyd(x, kmeans_pp_init(x, k, rng), max_iter)
        inertia = float(np.sum((x - centres[labels]) ** 2))
        if best is None or inertia < best.inertia - 1e-12:
            labels, centres = _renumber(labels, centres)
            best = KMeansResult(labels=labels, centres=centres, inertia=inertia)
    assert best is not None  # restarts >= 1 (internal invariant, not an input check)
    return best

"""Rotation averaging against the truth and against a slow, obvious minimiser of the same robust cost."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from mvgeo.align.rotation_averaging import _chordal, average_rotations
from mvgeo.common.errors import DegenerateGeometryError


def _ring_graph(n: int, seed: int, noise_deg: float, outliers: int):
    """Cameras on a ring looking inwards; pairs between neighbours up to 2 steps apart (a ring with chords)."""
    rng = np.random.default_rng(seed)
    R_true = Rotation.random(n, random_state=seed).as_matrix()
    R_true = R_true @ R_true[0].T  # view 0 at the identity
    rel, weight = {}, {}
    edges = [(i, (i + k) % n) for i in range(n) for k in (1, 2)]
    for i, j in edges:
        a, b = min(i, j), max(i, j)
        noise = Rotation.from_rotvec(np.radians(noise_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix()
        rel[(a, b)] = noise @ R_true[b] @ R_true[a].T
        weight[(a, b)] = float(rng.integers(30, 300))
    bad = list(rel)[3:3 + 4 * outliers:4]
    for e in bad:  # gross outliers, e.g. pairs matched across symmetric structure
        rel[e] = Rotation.from_rotvec(np.radians(60.0) * np.array([0.0, 1.0, 0.0])).as_matrix() @ rel[e]
    return R_true, rel, weight, bad


def _angle_deg(A, B) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(A @ B.T).as_rotvec())))


def _reference(n, rel, weight, R0, scale_deg):
    """The same robust cost, sum_e w_e s^2 log(1 + (|r_e| / s)^2), minimised by BFGS on rotation vectors."""
    edges = list(rel)
    w = np.array([weight[e] for e in edges])
    w = w / w.max()
    s = np.radians(scale_deg)

    def rot(x):
        return [np.eye(3)] + [Rotation.from_rotvec(x[3 * k:3 * k + 3]).as_matrix() @ R0[k + 1] for k in range(n - 1)]

    def cost(x):
        R = rot(x)
        total = 0.0
        for (i, j), we in zip(edges, w, strict=True):
            r = np.linalg.norm(Rotation.from_matrix(rel[(i, j)] @ R[i] @ R[j].T).as_rotvec())
            total += we * s * s * np.log1p((r / s) ** 2)
        return total

    x = minimize(cost, np.zeros(3 * (n - 1)), method="BFGS", options={"gtol": 1e-10, "maxiter": 2000}).x
    return np.stack(rot(x))


def test_exact_on_consistent_graph():
    R_true, rel, weight, _ = _ring_graph(9, seed=0, noise_deg=0.0, outliers=0)
    res = average_rotations(9, rel, weight)
    assert max(_angle_deg(a, b) for a, b in zip(res.R_cam_from_world, R_true, strict=True)) < 1e-6
    assert max(res.residual_deg.values()) < 1e-6


def test_chordal_is_the_linear_least_squares_solution_before_projection():
    # On a consistent graph the chordal solution is exact; on a noisy one each block is near a rotation.
    R_true, rel, weight, _ = _ring_graph(7, seed=3, noise_deg=1.0, outliers=0)
    R = _chordal(7, list(rel), [rel[e] for e in rel], np.ones(len(rel)))
    assert max(_angle_deg(a, b) for a, b in zip(R, R_true, strict=True)) < 2.0
    assert np.allclose(R @ np.transpose(R, (0, 2, 1)), np.eye(3), atol=1e-9)


def test_robust_to_outliers_and_matches_slow_reference():
    n = 10
    R_true, rel, weight, bad = _ring_graph(n, seed=1, noise_deg=0.5, outliers=2)
    res = average_rotations(n, rel, weight, robust_scale_deg=2.0)
    err = [_angle_deg(a, b) for a, b in zip(res.R_cam_from_world, R_true, strict=True)]
    assert max(err) < 1.0, err
    # The wrong pairs stand out by their residuals; the others are explained.
    assert min(res.residual_deg[e] for e in bad) > 30.0
    assert max(r for e, r in res.residual_deg.items() if e not in bad) < 3.0
    # Same minimum as the slow, obvious minimiser of the same cost started at the true rotations (the cost
    # is not convex: from a start skewed by the outliers a local minimiser can end elsewhere).
    ref = _reference(n, rel, weight, R_true, 2.0)
    assert max(_angle_deg(a, b) for a, b in zip(res.R_cam_from_world, ref, strict=True)) < 0.05


def test_chaining_drifts_where_averaging_does_not():
    # Chaining a 24-view ring's consecutive pairs adds their errors up; averaging over the chords does not.
    # Mean error over the views and over five graphs (one graph's noise can happen to cancel along the chain).
    n, chained_err, averaged_err = 24, [], []
    for seed in range(5):
        R_true, rel, weight, _ = _ring_graph(n, seed=seed, noise_deg=1.0, outliers=0)
        chained = [np.eye(3)]
        for k in range(1, n):
            chained.append(rel[(k - 1, k)] @ chained[-1])
        chained_err += [_angle_deg(a, b) for a, b in zip(chained, R_true, strict=True)]
        res = average_rotations(n, rel, weight)
        averaged_err += [_angle_deg(a, b) for a, b in zip(res.R_cam_from_world, R_true, strict=True)]
    assert np.mean(averaged_err) < 0.5 * np.mean(chained_err)


def test_disconnected_graph_is_refused():
    rel = {(0, 1): np.eye(3), (2, 3): np.eye(3)}
    with pytest.raises(DegenerateGeometryError, match="do not connect"):
        average_rotations(4, rel)

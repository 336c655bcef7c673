"""`mvgeo.align.loops`: loops of three pairs, the rotations they compare, and the rejection of false pairs."""


import numpy as np
import pytest

from mvgeo.align.loops import (
    all_triangles,
    pair_rotations,
    reject_by_loops,
    rotation_angle_deg,
    rotation_from_matches,
    rotation_from_pointmap,
    triangle_loops,
)
from mvgeo.transforms import so3_exp

from .synthetic import make_pairs, make_views

FOCAL = 30.0


def _random_rotation(rng, max_deg=180.0):
    axis = rng.normal(size=3)
    return so3_exp(axis / np.linalg.norm(axis) * np.radians(rng.uniform(0, max_deg)))


def _pose_graph(rng, n=10, keep=0.7, noise_deg=1.0):
    """Absolute rotations, and noisy relative ones (cam_j_from_cam_i) on a random connected graph."""
    R = [_random_rotation(rng) for _ in range(n)]
    edges = [(i, i + 1) for i in range(n - 1)]  # a path keeps it connected
    edges += [(i, j) for i in range(n) for j in range(i + 2, n) if rng.random() < keep]
    rel = {(i, j): _random_rotation(rng, noise_deg) @ R[j] @ R[i].T for i, j in edges}
    return R, rel


def test_triangle_enumeration_matches_brute_force(rng):
    _, rel = _pose_graph(rng, n=9, keep=0.5)
    assert sorted(triangle_loops(rel)) == all_triangles(9, list(rel))


def test_exact_loops_are_identity_and_nothing_is_rejected(rng):
    _, rel = _pose_graph(rng, n=8, keep=1.0, noise_deg=0.0)
    loops = triangle_loops(rel)
    assert len(loops) == 56 and max(loops.values()) < 1e-5  # float64 round-off of three products
    assert reject_by_loops(rel).removed == []


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planted_false_pairs_are_rejected_and_true_ones_kept(seed):
    rng = np.random.default_rng(seed)
    _, rel = _pose_graph(rng, n=12, keep=0.6, noise_deg=1.5)
    # Plant false pairs: relative rotations 40-120 deg away from the truth (repeated structure).
    candidates = [e for e in rel if e[1] - e[0] >= 2]
    false = [candidates[k] for k in rng.choice(len(candidates), size=4, replace=False)]
    for e in false:
        axis = rng.normal(size=3)
        rel[e] = so3_exp(axis / np.linalg.norm(axis) * np.radians(rng.uniform(40, 120))) @ rel[e]
    weights = {e: 100.0 for e in rel}
    for e in false:
        weights[e] = 200.0  # stronger than the true pairs: the vote, not the weights, must find them
    check = reject_by_loops(rel, weights)
    assert sorted(check.removed) == sorted(false)
    assert all(b > g for b, g in check.votes)


def test_a_false_pair_in_no_loop_cannot_be_judged_and_is_kept(rng):
    R = [_random_rotation(rng) for _ in range(4)]
    rel = {(0, 1): R[1] @ R[0].T, (1, 2): R[2] @ R[1].T, (0, 2): R[2] @ R[0].T,
           (2, 3): _random_rotation(rng) @ R[3] @ R[2].T}  # (2, 3) is a bridge
    assert reject_by_loops(rel).removed == []


def test_rotation_from_matches_and_from_pointmap_are_exact(rng):
    poses, depths = make_views(3)
    H, W = depths[0].shape
    K = np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1]])
    X = rng.uniform([-1, -1, 3.5], [1, 1, 5.5], size=(40, 3))

    def project(T):
        x = X @ T[:, :3].T + T[:, 3]
        return x[:, :2] / x[:, 2:] * FOCAL + K[:2, 2]

    uv = np.concatenate([project(poses[0]), project(poses[2])], axis=1)
    R_true = poses[2][:, :3] @ poses[0][:, :3].T
    # Noise-free matches: the linear essential matrix is exact up to round-off.
    assert rotation_angle_deg(rotation_from_matches(uv, K, K) @ R_true.T) < 1e-5
    pred = make_pairs(poses, depths, FOCAL, rng, pairs=[(0, 2)])[0]
    R_pm = rotation_from_pointmap(pred.pts_j.astype(np.float64), pred.conf_j, FOCAL)
    # PnP on float32 pointmaps of a 32x24 grid: ~1e-3 deg.
    assert rotation_angle_deg(R_pm @ R_true.T) < 0.01
    rel, _ = pair_rotations([], np.repeat(K[None], 3, 0), [pred])
    assert rotation_angle_deg(rel[(0, 2)] @ R_true.T) < 0.01


def test_thin_svd_essential_equals_the_reference(rng):
    from mvgeo.align.loops import essential_linear
    from mvgeo.epipolar import essential_from_linear

    x1 = rng.normal(size=(300, 2))
    x2 = x1 + 0.1 * rng.normal(size=(300, 2))  # noisy, not an exact essential configuration
    E, E_ref = essential_linear(x1, x2), essential_from_linear(x1, x2)
    assert min(np.abs(E - E_ref).max(), np.abs(E + E_ref).max()) < 1e-9  # same null vector up to sign

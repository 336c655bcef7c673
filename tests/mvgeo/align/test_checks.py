"""`mvgeo.align.checks`: each verified pair against the result (Sampson fraction, rotation deviation), and the
views none of whose pairs the result explains (against a slow reference)."""

import itertools

import numpy as np

from mvgeo.align.checks import PairCheck, pair_consistency, pair_rotation_deviation, views_without_consistent_pair
from mvgeo.transforms import so3_exp

from .synthetic import make_views, three_view_matches

FOCAL = 30.0


def test_pair_consistency_exact_and_wrong_geometry(rng):
    W, H, f = 320, 240, 300.0
    poses, matches = three_view_matches(rng, W=W, H=H, f=f)
    good = pair_consistency(poses, np.full(3, f), (W, H), matches)
    assert all(c.explained_fraction == 1.0 and c.n_matches == 80 for c in good)
    wrong = poses.copy()
    wrong[2, :, :3] = so3_exp(np.array([0.0, 0.0, 0.3])) @ wrong[2, :, :3]  # view 2 rolled by 17 deg
    bad = {(c.i, c.j): c.explained_fraction for c in pair_consistency(wrong, np.full(3, f), (W, H), matches)}
    assert bad[(0, 1)] == 1.0 and bad[(0, 2)] < 0.5 and bad[(1, 2)] < 0.5


def test_rotation_check_flags_a_pair_the_result_turns_away(rng):
    poses, _ = make_views(3)
    W, H = 32, 24
    X = rng.uniform([-1, -1, 3.5], [1, 1, 5.5], size=(40, 3))

    def project(T):
        x = X @ T[:, :3].T + T[:, 3]
        return x[:, :2] / x[:, 2:] * FOCAL + np.array([W / 2, H / 2])

    matches = [(0, 1, np.concatenate([project(poses[0]), project(poses[1])], axis=1)),
               (1, 2, np.concatenate([project(poses[1]), project(poses[2])], axis=1))]
    f = np.full(3, FOCAL)
    assert max(pair_rotation_deviation(poses, f, (W, H), matches)) < 1e-4  # exact data, float64
    turned = poses.copy()
    turned[2, :, :3] = so3_exp(np.radians([0.0, 20.0, 0.0])) @ poses[2][:, :3]
    dev = pair_rotation_deviation(turned, f, (W, H), matches)
    assert dev[0] < 1e-4 and abs(dev[1] - 20.0) < 1e-3


def _reference(checks, bad, n):
    """Slow and obvious: per view, list its pairs and ask whether each one is bad."""
    bad_keys = {(c.i, c.j) for c in bad}
    out = []
    for v in range(n):
        mine = [(c.i, c.j) for c in checks if v in (c.i, c.j)]
        if mine and all(k in bad_keys for k in mine):
            out.append(v)
    return out


def test_views_without_consistent_pair_match_the_reference_on_random_pair_graphs():
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(2, 9))
        all_pairs = list(itertools.combinations(range(n), 2))
        keep = rng.random(len(all_pairs)) < 0.5
        checks = [PairCheck(i, j, 50, 1.0) for (i, j), k in zip(all_pairs, keep, strict=True) if k]
        bad = [c for c in checks if rng.random() < 0.4]
        assert views_without_consistent_pair(checks, bad, n) == _reference(checks, bad, n)


def test_a_view_in_no_pair_is_not_judged():
    checks = [PairCheck(0, 1, 50, 1.0)]
    assert views_without_consistent_pair(checks, [], 3) == []
    assert views_without_consistent_pair(checks, checks, 3) == [0, 1]
    assert views_without_consistent_pair([], [], 3) == []

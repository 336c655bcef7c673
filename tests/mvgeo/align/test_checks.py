"""`mvgeo.align.checks`: each verified pair against the result (Sampson fraction, rotation deviation), and the
views none of whose pairs the result explains (against a slow reference)."""

import itertools

import numpy as np

from mvgeo.align.checks import PairCheck, pair_consistency, pair_rotation_deviation, views_cut_off
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
    """Slow and obvious: scipy's connected components of the explained pairs; the main group has the most
    views, then the most matches, then the lowest view; every other view in some checked pair is cut off."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    bad_keys = {(c.i, c.j) for c in bad}
    good = [c for c in checks if (c.i, c.j) not in bad_keys]
    adj = coo_matrix((np.ones(len(good)), ([c.i for c in good], [c.j for c in good])), shape=(n, n))
    _, label = connected_components(adj, directed=False)
    judged = sorted({v for c in checks for v in (c.i, c.j)})
    if not judged:
        return []
    groups = {lab: [v for v in judged if label[v] == lab] for lab in {label[v] for v in judged}}
    weight = {lab: sum(c.n_matches for c in good if label[c.i] == lab) for lab in groups}
    main = sorted(groups, key=lambda g: (-len(groups[g]), -weight[g], min(groups[g])))[0]
    return [v for v in judged if label[v] != main]


def _labels(pairs, n):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    adj = coo_matrix((np.ones(len(pairs)), ([c.i for c in pairs], [c.j for c in pairs])), shape=(n, n))
    return connected_components(adj, directed=False)


def _reference_linked(checks, bad, n, located, misplaced):
    """Slow and obvious: `_reference`'s cut-off views, less the located ones and the groups (connected by
    explained pairs) holding a located view and no misplaced one: of such a group, the parts that its weak
    bridges separate (an explained pair whose removal adds a component; 3 std of its rotation over 5 deg, or
    not measured) holding a located view."""
    bad_keys = {(c.i, c.j) for c in bad}
    good = [c for c in checks if (c.i, c.j) not in bad_keys]
    count, label = _labels(good, n)
    weak = [c for c in good if not 3.0 * c.rotation_std_deg <= 5.0
            and _labels([d for d in good if d is not c], n)[0] > count]
    _, part = _labels([c for c in good if c not in weak], n)
    cut = _reference(checks, bad, n)
    vouched = {label[v] for v in located if v in cut} - {label[v] for v in misplaced if v in cut}
    return [v for v in cut if v not in located
            and not (label[v] in vouched and any(part[w] == part[v] for w in located))]


def _random_pair_graph(rng, rotation_std=False):
    """(n, checks, bad): n views, each pair checked with probability 0.4, each check failing with probability
    0.3; with `rotation_std`, each pair's rotation pinned to 0.5 deg (strong), 3 deg or not measured (weak)."""
    n = int(rng.integers(2, 10))
    all_pairs = list(itertools.combinations(range(n), 2))
    keep = rng.random(len(all_pairs)) < 0.4

    def check(i, j):
        n_matches = int(rng.integers(20, 200))
        if not rotation_std:
            return PairCheck(i, j, n_matches, 1.0)
        return PairCheck(i, j, n_matches, 1.0, 1.0, float(rng.choice([0.5, 3.0, np.nan])))

    checks = [check(i, j) for (i, j), k in zip(all_pairs, keep, strict=True) if k]
    return n, checks, [c for c in checks if rng.random() < 0.3]


def test_views_cut_off_with_located_views_match_the_reference_on_random_pair_graphs():
    rng = np.random.default_rng(1)
    for _ in range(300):
        n, checks, bad = _random_pair_graph(rng, rotation_std=True)
        located = [v for v in range(n) if rng.random() < 0.3]
        misplaced = [v for v in range(n) if v not in located and rng.random() < 0.2]
        assert views_cut_off(checks, bad, n, located=located, misplaced=misplaced) == _reference_linked(
            checks, bad, n, located, misplaced)


def test_a_located_view_vouches_for_its_group_unless_one_is_placed_elsewhere():
    """A ring 0..7 broken at two gaps (0-1... 3 | 4..7 | 0): the links (3, 4) and (7, 0) contradicted, as weak
    pairs across held-out views are while the result is right. PnP locating one view of {4..7} on the main
    group's points links the whole group; a view of it that PnP puts confidently elsewhere does not allow it."""
    checks = [PairCheck(k, (k + 1) % 8, 100, 1.0, 1.0, 0.3) for k in range(8)]  # rotations pinned to 0.3 deg
    bad = [c for c in checks if (c.i, c.j) in ((3, 4), (7, 0))]
    assert views_cut_off(checks, bad, 8) == [4, 5, 6, 7]
    assert views_cut_off(checks, bad, 8, located=[6]) == []
    assert views_cut_off(checks, bad, 8, located=[6], misplaced=[5]) == [4, 5, 7]
    assert views_cut_off(checks, bad, 8, located=[2]) == [4, 5, 6, 7]  # a main-group view vouches for no other
    # {4, 5} hang on {6, 7} by the weak bridge (5, 6), whose matches do not pin its rotation: it needs a located
    # view of its own
    rigid = [PairCheck(c.i, c.j, 100, 1.0, 1.0, 2.5 if (c.i, c.j) == (5, 6) else 0.3) for c in checks]
    bad = [c for c in rigid if (c.i, c.j) in ((3, 4), (7, 0))]
    assert views_cut_off(rigid, bad, 8, located=[6]) == [4, 5]
    assert views_cut_off(rigid, bad, 8, located=[6, 4]) == []


def test_views_cut_off_match_the_reference_on_random_pair_graphs():
    rng = np.random.default_rng(0)
    for _ in range(300):
        n, checks, bad = _random_pair_graph(rng)
        assert views_cut_off(checks, bad, n) == _reference(checks, bad, n)


def test_a_view_in_no_pair_is_not_judged():
    checks = [PairCheck(0, 1, 50, 1.0)]
    assert views_cut_off(checks, [], 3) == []
    assert views_cut_off(checks, checks, 3) == [1]  # two singletons: the lower view is the main group
    assert views_cut_off([], [], 3) == []


def test_a_group_hinged_on_contradicted_pairs_is_cut_off():
    """An open chain of views 0-1-2-3-4-5 plus the triangle 3-4-5: the result explains every pair but the two
    that link {4, 5} to the rest, as a bent orbit does (each view keeps an explained pair)."""
    checks = [PairCheck(i, j, 60, 1.0) for i, j in ((0, 1), (1, 2), (2, 3), (3, 4), (3, 5), (4, 5))]
    bad = [c for c in checks if (c.i, c.j) in ((3, 4), (3, 5))]
    assert views_cut_off(checks, bad, 6) == [4, 5]
    assert views_cut_off(checks, bad[:1], 6) == []  # one link left: the group is supported

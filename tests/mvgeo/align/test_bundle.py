"""`mvgeo.align.bundle`: `build_tracks` (connected components of the matches) against the union-find reference."""

import numpy as np
import pytest

from mvgeo.align.bundle import build_tracks, build_tracks_reference


def _random_matches(rng, n_views=6, n_kp=60, n_pairs=12, m=10):
    """Matches between random keypoints of random view pairs: shared keypoints chain into tracks,
    and repeated draws create conflicts (two keypoints of one view in one track)."""
    kps = [np.round(rng.uniform(0, 100, (n_kp, 2)), 1) for _ in range(n_views)]
    out = []
    for _ in range(n_pairs):
        i, j = rng.choice(n_views, 2, replace=False)
        a, b = rng.integers(0, n_kp, m), rng.integers(0, n_kp, m)
        out.append((int(i), int(j), np.concatenate([kps[i][a], kps[j][b]], axis=1)))
    return out


@pytest.mark.parametrize("seed", range(8))
def test_components_match_union_find_reference_exactly(seed):
    rng = np.random.default_rng(seed)
    matches = _random_matches(rng)
    fast, ref = build_tracks(matches), build_tracks_reference(matches)
    for x, y in zip(fast, ref, strict=True):
        np.testing.assert_array_equal(x, y)
    # The random draws must exercise both kept and dropped (conflicting) tracks.
    assert len(ref[0]) > 0
    n_keypoints = len({(i, *r[:2]) for i, _, uv in matches for r in uv} | {(j, *r[2:]) for _, j, uv in matches
                                                                        for r in uv})
    assert len(ref[0]) < n_keypoints


def test_chain_and_conflict_by_hand():
    # 0:(1,1) - 1:(2,2) - 2:(3,3) chains into one track; 3:(5,5) matched to two keypoints of view 4 is dropped.
    matches = [(0, 1, np.array([[1.0, 1, 2, 2]])), (1, 2, np.array([[2.0, 2, 3, 3]])),
               (3, 4, np.array([[5.0, 5, 6, 6], [5, 5, 7, 7]]))]
    view, track, uv = build_tracks(matches)
    np.testing.assert_array_equal(view, [0, 1, 2])
    np.testing.assert_array_equal(track, [0, 0, 0])
    np.testing.assert_array_equal(uv, [[1, 1], [2, 2], [3, 3]])


def test_empty_input():
    for out in (build_tracks([]), build_tracks([(0, 1, np.zeros((0, 4)))])):
        assert [len(x) for x in out] == [0, 0, 0]
        assert out[2].shape == (0, 2)

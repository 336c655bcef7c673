"""A view whose every verified pair contradicts the reconstruction is not registered (`views_without_consistent_pair`).

The whole-result check (`max_unexplained_fraction`) weighs pairs by their matches, so one wrong view with few
matches passes it: measured on object_ring rendered with 32 views (28 training views), where view_001 came out
6.3 m off on a 3 m ring with every one of its four pairs 69-72 deg off its matches, and `mvgeo align` returned
it (CHANGELOG.md, 2026-11-25).
"""

import itertools

import numpy as np
import pytest

from mvgeo.align.api import AlignConfig, _consistency_error, _Solution
from mvgeo.align.checks import PairCheck, views_without_consistent_pair
from mvgeo.common.errors import DegenerateGeometryError


def _reference(checks, bad, n):
    """Slow and obvious: per view, list its pairs and ask whether each one is bad."""
    bad_keys = {(c.i, c.j) for c in bad}
    out = []
    for v in range(n):
        mine = [(c.i, c.j) for c in checks if v in (c.i, c.j)]
        if mine and all(k in bad_keys for k in mine):
            out.append(v)
    return out


def test_matches_the_reference_on_random_pair_graphs():
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


def _solution(checks, bad, names):
    # _consistency_error reads only the checks, the names and the focal/bundle fields.
    return _Solution(None, [], [], names, [], [], None, None, None, checks, bad, None, 1.0, 0, 0, [], [], [], [],
                     focal_determined=True)


def test_the_alignment_fails_naming_a_view_all_of_whose_pairs_contradict_it():
    names = [f"view_{k:03d}.png" for k in range(6)]
    # A ring of five consistent pairs with many matches; view 5 has two pairs with few matches, both bad.
    good = [PairCheck(k, (k + 1) % 5, 1000, 0.97, 0.3) for k in range(5)]
    wrong = [PairCheck(0, 5, 40, 0.05, 70.0), PairCheck(4, 5, 30, 0.23, 72.0)]
    sol = _solution(good + wrong, wrong, names)
    # 70 of 5070 matches unexplained: under the whole-result limit, so only the per-view check can see it.
    assert 70 / 5070 < AlignConfig().max_unexplained_fraction
    err = _consistency_error(sol, AlignConfig())
    assert isinstance(err, DegenerateGeometryError)
    msg = str(err)
    assert "every verified image pair of 1 of 6 views" in msg and "view_005.png" in msg
    assert "with view_000.png: 5% explained, rotation 70 deg off" in msg and "--allow-partial" in msg
    # The switch: off, the result passes (the whole-result fraction is under its limit).
    assert _consistency_error(sol, AlignConfig(reject_unsupported_views=False)) is None


def test_one_consistent_pair_is_enough():
    names = [f"view_{k:03d}.png" for k in range(6)]
    good = [PairCheck(k, (k + 1) % 5, 1000, 0.97, 0.3) for k in range(5)] + [PairCheck(0, 5, 40, 0.9, 1.0)]
    wrong = [PairCheck(4, 5, 30, 0.23, 72.0)]
    assert _consistency_error(_solution(good + wrong, wrong, names), AlignConfig()) is None


@pytest.mark.slow
def test_denser_orbit_with_an_unsupported_view_is_a_specific_failure(tmp_path):
    """object_ring with 32 views at 256x192: 28 training views (11.25 deg steps, four 22.5 deg gaps). Before
    this check `mvgeo align` returned view_001 6.3 m off (ATE 1.39 m on a 3 m ring, median relative rotation
    error 3.6 deg). Now it fails naming view_001; with `allow_partial` it registers a subset that is right:
    measured 14 of 28 at 0.62 deg median relative rotation error and ATE 0.017 m. The bounds (1.5 deg, 0.05 m)
    lie between that and the bent results seen on this ring (3.6-5.1 deg, ATE 0.11-1.39 m)."""
    import json
    from dataclasses import replace

    from data_synth import render_scene
    from mvgeo.align.api import align_images
    from mvgeo.align.dense_stereo import DenseStereoConfig
    from mvgeo.common.imageio import list_images
    from mvgeo.metrics import compare_poses
    from mvgeo.sparse_model import read_sparse_model

    d = render_scene("object_ring", tmp_path / "ring", size_wh=(256, 192), views=32)
    train = json.loads((d / "split.json").read_text())["train"]
    paths = [p for p in list_images(d / "images") if p.name in train]
    cfg = replace(AlignConfig(), dense_stereo=DenseStereoConfig(enabled=False))
    with pytest.raises(DegenerateGeometryError, match="contradicts every verified image pair") as info:
        align_images(paths, cfg)
    assert "view_001.png" in str(info.value)
    res = align_images(paths, replace(cfg, allow_partial=True))
    m = compare_poses(res.sparse_model.cam_from_world_by_name(),
                      read_sparse_model(d / "sparse" / "0").cam_from_world_by_name())
    assert m.n_registered >= 3
    assert m.median_rotation_deg < 1.5 and m.ate.rmse < 0.05

"""`mvgeo.align.init`: the rule that picks the first start, and each start's initial values (exact on exact
pointmaps), with the pair-pose chaining where rotation averaging fails."""

from dataclasses import replace

import numpy as np
import pytest

import mvgeo.align.init as init_mod
from mvgeo.align.global_align import GlobalAlignConfig, global_align
from mvgeo.align.init import STARTS, chain_contradicted_fraction, choose_start, initial_values, other_start
from mvgeo.align.pairs import PairGeometry, PairSet
from mvgeo.align.pose_chain import init_from_pair_poses
from mvgeo.align.solve import naming_views
from mvgeo.common.errors import DegenerateGeometryError, UnposedViewsError
from mvgeo.metrics import compare_poses
from mvgeo.transforms import R_from_axis_angle

from .synthetic import make_matches, make_pairs, make_views

FOCAL = 30.0


def _pair_set(preds, matches=()):
    return PairSet(preds, [], [PairGeometry(i, j, uv) for i, j, uv in matches], focal_determined=True)


def test_the_first_start_rule():
    limit = init_mod.CHAIN_MAX_CONTRADICTED
    assert choose_start("auto") == "chain"  # not measured: chaining first
    assert choose_start("auto", limit) == "chain" and choose_start("auto", float("nan")) == "chain"
    assert choose_start("auto", limit + 0.01) == "averaged"  # the chained start contradicts most pairs
    for start in STARTS:
        for measured in (None, 0.0, 1.0):
            assert choose_start(start, measured) == start  # a configured start is never overridden
        assert other_start(start) != start and other_start(other_start(start)) == start
    assert set(STARTS) == {"chain", "averaged"}


def test_the_chained_start_contradicts_the_pairs_it_turns_past_the_limit(rng):
    poses, _ = make_views(5)
    R = poses[:, :, :3]
    exact = {(i, j): R[j] @ R[i].T for i in range(5) for j in range(i + 1, 5)}
    assert chain_contradicted_fraction(poses, exact, 10.0) == 0.0
    assert np.isnan(chain_contradicted_fraction(poses, {}, 10.0))
    # Turn 6 of the 10 pairs by 8, 9.5, 11, ... 15.5 deg: 4 of them past 10 deg, 5 past 9 deg, 6 past 7.9.
    turned = dict(exact)
    for k, key in enumerate(sorted(exact)[:6]):
        axis = rng.normal(size=3)
        turned[key] = R_from_axis_angle(axis / np.linalg.norm(axis) * np.radians(8.0 + 1.5 * k)) @ exact[key]
    assert chain_contradicted_fraction(poses, turned, 10.0) == pytest.approx(0.4)
    assert chain_contradicted_fraction(poses, turned, 9.0) == pytest.approx(0.5)
    assert chain_contradicted_fraction(poses, turned, 7.9) == pytest.approx(0.6)


def test_pair_relative_rotations_take_the_models_pose_else_the_matches(rng):
    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng)
    matches = {(i, j): uv for i, j, uv in make_matches(poses, depths, FOCAL, [(p.i, p.j) for p in preds])}
    R = poses[:, :, :3]
    keys = sorted(matches)
    K = np.repeat(np.array([[[FOCAL, 0, 16.0], [0, FOCAL, 12.0], [0, 0, 1]]]), 4, axis=0)
    marker = R_from_axis_angle(np.array([0.0, 0.0, 0.3]))  # a pose the model reports, not the true one
    geoms = [PairGeometry(i, j, matches[(i, j)], np.c_[marker, np.zeros(3)] if k == 0 else None)
             for k, (i, j) in enumerate(keys)]
    rel = init_mod.pair_relative_rotations(PairSet(preds, [], geoms, focal_determined=True), K)
    assert set(rel) == {(min(p.i, p.j), max(p.i, p.j)) for p in preds}
    np.testing.assert_allclose(rel[keys[0]], marker)  # the model's own pose, as given
    for i, j in keys[1:]:  # from the exact matches
        np.testing.assert_allclose(rel[(i, j)], R[j] @ R[i].T, atol=1e-6)
    flipped = [PairGeometry(keys[0][1], keys[0][0], matches[keys[0]][:, [2, 3, 0, 1]], np.c_[marker.T, np.zeros(3)])]
    rel = init_mod.pair_relative_rotations(PairSet([], [], flipped, focal_determined=True), K)
    np.testing.assert_allclose(rel[keys[0]], marker)  # stored as (i < j): transposed back


@pytest.mark.parametrize("known", [False, True])
@pytest.mark.parametrize("shared_focal", [False, True])
def test_the_chain_start_is_dusts_spanning_tree_chaining(rng, known, shared_focal):
    """The chained start's values are `init_from_spanning_tree`'s at the focal the alignment would use (the
    known one; else the pairs' estimates, one geometric mean with a shared focal), so the alignment from them
    is the alignment that initialises itself by chaining; exact on exact pointmaps at the true focal."""
    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng)
    for k, p in enumerate(preds):  # pair focal estimates 0 and 8 % off: each focal rule gives other values
        p.focal_i_px = p.focal_j_px = FOCAL * (1.0 + 0.08 * (k % 2))
    sizes = [d.shape for d in depths]
    focal = np.full(4, FOCAL) if known else None
    align = GlobalAlignConfig(init="pair_poses", shared_focal=shared_focal, optimize_focal=not known)
    cfg, init, made_by = initial_values("chain", _pair_set(preds), sizes, focal, align, 1.0, (32, 24))
    assert cfg.init == "procrustes" and made_by == "chained_pointmaps"
    given = global_align(preds, sizes, config=replace(cfg, iters=5), focal_init_px=focal, init=init)
    itself = global_align(preds, sizes, config=replace(cfg, iters=5), focal_init_px=focal)
    np.testing.assert_array_equal(given.cam_from_world, itself.cam_from_world)
    np.testing.assert_array_equal(given.focal_px, itself.focal_px)
    if known:
        np.testing.assert_array_equal(init.focal_px, FOCAL)
        names = [str(k) for k in range(4)]
        m = compare_poses(dict(zip(names, init.cam_from_world, strict=True)), dict(zip(names, poses, strict=True)))
        assert m.median_rotation_deg < 0.01 and m.ate.rmse < 1e-3
    elif shared_focal:
        np.testing.assert_allclose(init.focal_px, init.focal_px[0])
        assert FOCAL < init.focal_px[0] < 1.08 * FOCAL


def test_the_averaged_start_is_exact_on_exact_pointmaps_and_tracks(rng, caplog):
    """Rotation averaging and global positioning on exact tracks: the true poses (up to the gauge)."""
    poses, depths = make_views(5)
    preds = make_pairs(poses, depths, FOCAL, rng)
    matches = make_matches(poses, depths, FOCAL, [(p.i, p.j) for p in preds])
    assert min(len(uv) for *_, uv in matches) > 20
    sizes = [d.shape for d in depths]
    with caplog.at_level("WARNING", logger="mvgeo.align.init"):
        cfg, init, made_by = initial_values("averaged", _pair_set(preds, matches), sizes, np.full(5, FOCAL),
                                            GlobalAlignConfig(), 1.0, (32, 24))
    assert cfg.init == "pair_poses" and init is not None and not caplog.text  # positioned on the tracks
    assert made_by == "averaged_positions"
    names = [str(k) for k in range(5)]
    m = compare_poses(dict(zip(names, init.cam_from_world, strict=True)), dict(zip(names, poses, strict=True)))
    assert m.median_rotation_deg < 0.01 and m.ate.rmse < 1e-3, m
    np.testing.assert_allclose(init.focal_px, FOCAL)


@pytest.mark.parametrize("shared_focal", [False, True])
def test_the_averaged_start_without_tracks_chains_the_pair_translations(rng, caplog, shared_focal):
    """No matches: the positions come from the pairs' own translation directions (chained); the focals are the
    pairs' estimates, one geometric mean for every view with a shared focal."""
    poses, depths = make_views(5)
    preds = make_pairs(poses, depths, FOCAL, rng)
    for k, p in enumerate(preds):  # pair focal estimates 0 and 4 % off
        p.focal_i_px = p.focal_j_px = FOCAL * (1.0 + 0.04 * (k % 2))
    sizes = [d.shape for d in depths]
    with caplog.at_level("WARNING", logger="mvgeo.align.init"):
        cfg, init, made_by = initial_values("averaged", _pair_set(preds), sizes, None,
                                            GlobalAlignConfig(shared_focal=shared_focal), 1.0, (32, 24))
    assert "chaining the pairs' poses" in caplog.text and made_by == "averaged_rotations"
    assert cfg.init == "pair_poses" and init is not None
    if shared_focal:
        np.testing.assert_allclose(init.focal_px, init.focal_px[0])
        assert FOCAL < init.focal_px[0] < 1.04 * FOCAL
    else:
        assert np.all((init.focal_px > FOCAL - 1e-4) & (init.focal_px < 1.04 * FOCAL + 1e-4))
    names = [str(k) for k in range(5)]
    m = compare_poses(dict(zip(names, init.cam_from_world, strict=True)), dict(zip(names, poses, strict=True)))
    assert m.median_rotation_deg < 0.1  # measured 0.018 deg: the pairs' focal errors turn their PnP rotations


def test_the_averaged_start_falls_back_to_the_pair_poses_when_averaging_fails(rng, monkeypatch):
    def fails(*args, **kwargs):
        raise DegenerateGeometryError("the pairs with a rotation do not connect the views")

    monkeypatch.setattr(init_mod, "init_from_averaged_rotations", fails)
    poses, depths = make_views(3)
    preds = make_pairs(poses, depths, FOCAL, rng)
    cfg, init, made_by = initial_values("averaged", _pair_set(preds), [d.shape for d in depths], None,
                                        GlobalAlignConfig(), 1.0, (32, 24))
    assert cfg.init == "pair_poses" and init is None  # `global_align` chains the pairs' own poses
    assert made_by == "chained_pair_poses"


def test_pair_pose_chaining_init_is_exact_on_exact_pointmaps(rng):
    poses, depths = make_views(5)
    preds = make_pairs(poses, depths, FOCAL, rng)
    init = init_from_pair_poses(preds, [d.shape for d in depths], focal_init_px=np.full(5, FOCAL))
    names = [str(k) for k in range(5)]
    m = compare_poses(dict(zip(names, init.cam_from_world, strict=True)), dict(zip(names, poses, strict=True)))
    # Exact float32 pointmaps and the true focal: PnP + depth-ratio chaining, ~1e-4 deg / 1e-5 units.
    assert m.median_rotation_deg < 0.01 and m.ate.rmse < 1e-3
    res = global_align(preds, [d.shape for d in depths], config=GlobalAlignConfig(iters=0, init="pair_poses"),
                       focal_init_px=np.full(5, FOCAL))
    # The alignment rescales the world (pinned pair scales): same rotations (float32 round-off).
    assert np.allclose(res.cam_from_world[:, :, :3], init.cam_from_world[:, :, :3], atol=1e-5)


def test_a_chain_that_cannot_reach_every_view_names_the_views_it_left_out(rng):
    """Pointmaps of two separate pairs: the chained start raises `UnposedViewsError` with the indices of the
    pair it could not reach; the solve names them by file (`solve.naming_views`)."""
    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng, pairs=[(0, 1), (2, 3)])
    sizes = [d.shape for d in depths]
    with pytest.raises(UnposedViewsError) as info:
        initial_values("chain", _pair_set(preds), sizes, None, GlobalAlignConfig(), 1.0, (32, 24))
    assert set(info.value.views) in ({0, 1}, {2, 3}) and info.value.names is None
    names = ["a.png", "b.png", "c.png", "d.png"]
    with pytest.raises(UnposedViewsError) as named:
        with naming_views(names):
            raise info.value
    assert named.value.views == info.value.views
    assert str([names[v] for v in info.value.views]) in str(named.value)
    assert "not connected to the others" in str(named.value)

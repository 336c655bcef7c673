"""Loop-consistency rejection of false pairs, disconnected graphs and partial registration."""

from dataclasses import replace

import numpy as np
import pytest

from mvgeo.align.api import AlignConfig, align_images
from mvgeo.align.checks import pair_rotation_deviation
from mvgeo.align.global_align import GlobalAlignConfig, global_align
from mvgeo.align.loops import (
    all_triangles,
    pair_rotations,
    reject_by_loops,
    rotation_angle_deg,
    rotation_from_matches,
    rotation_from_pointmap,
    triangle_loops,
)
from mvgeo.align.pose_chain import init_from_pair_poses
from mvgeo.common.errors import InputError
from mvgeo.metrics import compare_poses, relative_pose_errors
from mvgeo.transforms import so3_exp

from .synthetic import look_at, make_pairs, make_views

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


class _FakeModel:
    """A PointmapModel that returns precomputed predictions (no matches: no bundle adjustment)."""

    pointmap_size_px = 32

    def __init__(self, preds):
        self.preds = preds

    def predict_pairs(self, images, pairs):
        return list(self.preds), []


def _images(rng, n, H=24, W=32):
    return [rng.random((H, W, 3)).astype(np.float32) for _ in range(n)]


FAST = AlignConfig(align=GlobalAlignConfig(iters=40), max_size_px=32, points_budget=2000)


def _false_pair(poses, depths, i, j, rng, deg=50.0):
    """Pair (i, j) predicted as if view j sat elsewhere on the orbit (a confusion with another view)."""
    wrong = poses.copy()
    C = -poses[j][:, :3].T @ poses[j][:, 3]
    a = np.radians(deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    centre = np.array([0.0, 0.0, 4.0]) + Ry @ (C - np.array([0.0, 0.0, 4.0]))
    wrong[j] = look_at(centre, np.array([0.0, 0.0, 4.0]))
    return make_pairs(wrong, depths, FOCAL, rng, pairs=[(i, j)])[0]


def test_align_rejects_a_planted_false_pair(rng):
    poses, depths = make_views(6)
    preds = make_pairs(poses, depths, FOCAL, rng, noise=0.002)
    false = _false_pair(poses, depths, 1, 4, rng)
    preds = [false if (p.i, p.j) == (1, 4) else p for p in preds]
    names = [f"v{k}.png" for k in range(6)]
    res = align_images(_images(rng, 6), FAST, names=names, model=_FakeModel(preds))
    rejected = [(r["i"], r["j"]) for r in res.stats["pairs_rejected_by_loops"]]
    assert rejected == [("v1.png", "v4.png")]
    est = res.sparse_model.cam_from_world_by_name()
    err = relative_pose_errors(np.stack([est[k] for k in names]), poses).rotation_deg
    # The DUSt3R objective (a norm, not squared) already resists one false pair; still, the worst
    # relative rotation was measured at 0.24 deg with the loop check and 0.45 deg without it.
    assert len(est) == 6 and err.max() < 0.35


def _two_groups(rng):
    poses, depths = make_views(5)
    return poses, make_pairs(poses, depths, FOCAL, rng, pairs=[(0, 1), (1, 2), (0, 2), (3, 4)])


def test_disconnected_graph_error_names_the_images(rng):
    _, preds = _two_groups(rng)
    names = [f"v{k}.png" for k in range(5)]
    with pytest.raises(InputError) as info:
        align_images(_images(rng, 5), FAST, names=names, model=_FakeModel(preds))
    msg = str(info.value)
    assert "disconnected" in msg and "['v3.png', 'v4.png']" in msg and "--allow-partial" in msg


def test_allow_partial_registers_the_largest_group_and_lists_the_others(rng):
    poses, preds = _two_groups(rng)
    names = [f"v{k}.png" for k in range(5)]
    cfg = AlignConfig(align=FAST.align, max_size_px=32, points_budget=2000, allow_partial=True)
    res = align_images(_images(rng, 5), cfg, names=names, model=_FakeModel(preds))
    est = res.sparse_model.cam_from_world_by_name()
    assert sorted(est) == ["v0.png", "v1.png", "v2.png"]
    assert [u["name"] for u in res.stats["unregistered"]] == ["v3.png", "v4.png"]
    assert res.stats["n_images"] == 5 and res.stats["n_registered"] == 3
    m = compare_poses(est, dict(zip(names, poses, strict=True)))
    assert m.median_rotation_deg < 0.5  # exact pointmaps
    assert all(np.isfinite(res.points_xyz).all(axis=1))


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


def test_allow_partial_drops_views_whose_pairs_the_result_contradicts(rng, monkeypatch):
    """Control flow: a pair judged inconsistent whose removal cuts a view off -> that view is unregistered
    (with allow_partial) and the rest is solved again; without allow_partial the result fails."""
    import mvgeo.align.api as api
    from mvgeo.align.checks import PairCheck
    from mvgeo.common.errors import DegenerateGeometryError

    poses, depths = make_views(5)
    pairs = [(0, 1), (1, 2), (0, 2), (2, 3), (1, 3), (3, 4)]
    preds = make_pairs(poses, depths, FOCAL, rng, pairs=pairs)
    for p in preds:  # one dummy match row per pair so that the judgement runs
        p.matches_px = np.zeros((1, 4))
    names = [f"v{k}.png" for k in range(5)]
    calls = []

    def judge(res, s_pm, size_wh, matches, thr, config):
        calls.append(len(res.cam_from_world))
        checks = [PairCheck(i, j, 10, 1.0, 0.0) for i, j, _ in matches]
        bad = [c for c in checks if len(calls) == 1 and (c.i, c.j) == (3, 4)]
        return checks, bad

    monkeypatch.setattr(api, "_judge", judge)
    # init_fallback off: the fake judgement finds the pair bad on the first call only, so a second start
    # (`test_init_fallback.py`) would pass.
    cfg = AlignConfig(align=FAST.align, max_size_px=32, points_budget=2000, bundle_adjust=False, loop_check=False,
                      init_fallback=False)
    with pytest.raises(DegenerateGeometryError, match="v3.png, v4.png"):
        align_images(_images(rng, 5), cfg, names=names, model=_FakeModel(preds))
    calls.clear()
    res = align_images(_images(rng, 5), replace(cfg, allow_partial=True), names=names, model=_FakeModel(preds))
    assert calls == [5, 4, 4]  # first solve, solve of the 4 kept views, final judgement with every pair
    assert sorted(res.sparse_model.cam_from_world_by_name()) == names[:4]
    assert res.stats["unregistered"] == [{"name": "v4.png", "reason":
                                          "its pairs are inconsistent with the reconstruction of the others"}]
    assert res.stats["pairs_dropped_as_inconsistent"] == [["v3.png", "v4.png"]]


def test_thin_svd_essential_equals_the_reference(rng):
    from mvgeo.align.loops import essential_linear
    from mvgeo.epipolar import essential_from_linear

    x1 = rng.normal(size=(300, 2))
    x2 = x1 + 0.1 * rng.normal(size=(300, 2))  # noisy, not an exact essential configuration
    E, E_ref = essential_linear(x1, x2), essential_from_linear(x1, x2)
    assert min(np.abs(E - E_ref).max(), np.abs(E + E_ref).max()) < 1e-9  # same null vector up to sign

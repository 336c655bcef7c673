"""Pair graphs, spanning tree order, co-visibility pruning and confidence-aware downsampling."""

import numpy as np
import pytest

from mvgeo.align.global_align import pixel_rays
from mvgeo.align.graph import PairGraphSpec, components, make_pairs, maximum_spanning_tree
from mvgeo.align.scene import covisibility_keep, voxel_downsample_by_confidence
from mvgeo.common.errors import ConfigError


def test_pair_graphs():
    assert len(make_pairs(5, PairGraphSpec.parse("complete"))) == 10
    assert len(make_pairs(30, PairGraphSpec.parse("auto"))) == 30 * 8  # window of 8 beyond 24 images
    w = make_pairs(6, PairGraphSpec.parse("window:2"))
    assert (0, 1) in w and (0, 2) in w and (0, 3) not in w and (4, 0) not in w and (0, 4) in w  # wraps around
    with pytest.raises(ConfigError, match="pairs"):
        PairGraphSpec.parse("window:x")


def test_maximum_spanning_tree_brute_force(rng):
    n = 5
    edges = [(i, j) for i in range(n) for j in range(i + 1, n)]
    scores = rng.random(len(edges)) + 0.1
    order = maximum_spanning_tree(n, edges, scores)
    assert len(order) == n - 1
    reached = set(edges[order[0]])
    for k in order[1:]:  # chaining order: every edge touches a reached view
        assert reached & set(edges[k])
        reached |= set(edges[k])
    # Brute force over all spanning trees (125 for K5 among C(10,4)=210 subsets).
    import itertools
    best = max(sum(scores[list(c)]) for c in itertools.combinations(range(len(edges)), n - 1)
                if len(components(n, [edges[k] for k in c])) == 1)
    assert sum(scores[order]) == pytest.approx(best)


def test_covisibility_keeps_each_surface_once():
    # Two identical cameras looking at the same plane: every pixel is seen twice; keep the more confident copy.
    H, W, f = 6, 8, 8.0
    cam = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
    depth = np.full((H, W), 2.0)
    pts = pixel_rays(H, W, f) * depth[..., None]
    conf_a = np.full((H, W), 3.0)
    conf_b = np.full((H, W), 2.0)
    conf_b[0, 0] = 5.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    keep = covisibility_keep([pts, pts], [depth, depth], [conf_a, conf_b], np.stack([cam, cam]), [K, K])
    assert keep[0].sum() == H * W - 1 and not keep[0][0, 0]
    assert keep[1].sum() == 1 and keep[1][0, 0]


def test_consistency_check_drops_only_contradicted_unconfirmed_points():
    """Multi-view fusion's geometric check: view 1 sees a plane at depth 2 where view 0 looks; view 0
    claims one pixel at 1.5 and one at 3.0 (no view confirms them: dropped), the rest at 2.02 (confirmed
    within 5 %, kept); a view-0 pixel that view 1 does not see (view 1's depth there is missing) is kept."""
    H, W, f = 6, 8, 8.0
    cam = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    d0 = np.full((H, W), 2.02)
    d0[1, 1], d0[2, 2] = 1.5, 3.0
    d0[4, 6] = 1.0  # unconfirmed, but view 1 has no depth there: nothing contradicts it
    d1 = np.full((H, W), 2.0)
    d1[4, 6] = np.nan
    pts0, pts1 = pixel_rays(H, W, f) * d0[..., None], pixel_rays(H, W, f) * d1[..., None]
    conf0, conf1 = np.full((H, W), 3.0), np.full((H, W), 2.0)  # view 0 wins the co-visibility pruning
    args = ([pts0, pts1], [d0, d1], [conf0, conf1], np.stack([cam, cam]), [K, K])
    keep = covisibility_keep(*args, consistency_rel_tol=0.05)
    assert not keep[0][1, 1] and not keep[0][2, 2] and keep[0][4, 6] and keep[0].sum() == H * W - 2
    off = covisibility_keep(*args)  # the check off: every view-0 point stays
    assert off[0].sum() == H * W


def test_free_space_check_drops_points_another_view_sees_through():
    """View 1 sees a plane at depth 2 everywhere; view 0 claims one pixel at 1.5 (view 1 sees through it:
    dropped) and one at 3.0 (behind what view 1 sees: occluded there, not a violation, kept); the rest
    agree. Only the free-space check is on."""
    H, W, f = 6, 8, 8.0
    cam = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    d0 = np.full((H, W), 2.0)
    d0[1, 1], d0[2, 2] = 1.5, 3.0
    d1 = np.full((H, W), 2.0)
    pts0, pts1 = pixel_rays(H, W, f) * d0[..., None], pixel_rays(H, W, f) * d1[..., None]
    conf0, conf1 = np.full((H, W), 3.0), np.full((H, W), 2.0)
    args = ([pts0, pts1], [d0, d1], [conf0, conf1], np.stack([cam, cam]), [K, K])
    keep = covisibility_keep(*args, rel_depth_tol=0.03, free_space_rel_tol=0.05)
    assert not keep[0][1, 1] and keep[0][2, 2] and keep[0].sum() == H * W - 1
    # Within the tolerance (1.95 vs 2.0: 2.5 % nearer) nothing is dropped.
    d0[1, 1] = 1.95
    pts0 = pixel_rays(H, W, f) * d0[..., None]
    keep = covisibility_keep([pts0, pts1], [d0, d1], [conf0, conf1], np.stack([cam, cam]), [K, K],
                             rel_depth_tol=0.0, free_space_rel_tol=0.05)
    assert keep[0].all()


def test_filled_depth_neither_carves_nor_vetoes_measured_points():
    """View 1's depth is a hole-filled guess at 3.0 behind the plane at 2.0 that view 0 measured: as evidence
    it would see through every view-0 point (free space) and confirm none (consistency), dropping them all.
    Marked as filled (not measured), it drops nothing; measured, it drops everything."""
    H, W, f = 6, 8, 8.0
    cam = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    d0, d1 = np.full((H, W), 2.0), np.full((H, W), 3.0)
    pts0, pts1 = pixel_rays(H, W, f) * d0[..., None], pixel_rays(H, W, f) * d1[..., None]
    conf0, conf1 = np.full((H, W), 3.0), np.full((H, W), 2.5)
    args = ([pts0, pts1], [d0, d1], [conf0, conf1], np.stack([cam, cam]), [K, K])
    tols = {"rel_depth_tol": 0.03, "consistency_rel_tol": 0.05, "free_space_rel_tol": 0.05}
    measured = [np.ones((H, W), bool), np.zeros((H, W), bool)]
    assert covisibility_keep(*args, **tols, measured=measured)[0].all()
    assert not covisibility_keep(*args, **tols)[0].any()
    # View 1's own filled points stay subject to view 0's measured depth, which sees them and contradicts them.
    assert not covisibility_keep(*args, **tols, measured=measured)[1].any()


def test_filled_points_are_checked_against_other_filled_depth():
    """Guesses are checked against guesses: with both views filled, view 1's guess at 3.0 sees through view
    0's guess at 2.0 and confirms none of it, so view 0's filled points go (as a backdrop no stereo measures
    must not keep every interpolated point); where view 1's guess agrees (2.02), they stay."""
    H, W, f = 6, 8, 8.0
    cam = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    tols = {"rel_depth_tol": 0.0, "consistency_rel_tol": 0.05, "free_space_rel_tol": 0.05}
    none_measured = [np.zeros((H, W), bool), np.zeros((H, W), bool)]
    conf = [np.full((H, W), 3.0), np.full((H, W), 2.5)]
    d0 = np.full((H, W), 2.0)
    for d1_value, kept in [(3.0, False), (2.02, True)]:
        d1 = np.full((H, W), d1_value)
        pts = [pixel_rays(H, W, f) * d0[..., None], pixel_rays(H, W, f) * d1[..., None]]
        keep = covisibility_keep(pts, [d0, d1], conf, np.stack([cam, cam]), [K, K], **tols, measured=none_measured)
        assert keep[0].all() == kept and keep[0].any() == kept


def test_voxel_downsample_budget_and_confidence(rng):
    pts = rng.random((5000, 3))
    conf = rng.random(5000)
    sel = voxel_downsample_by_confidence(pts, conf, 500)
    assert 250 < len(sel) <= 500
    assert conf[sel].mean() > conf.mean()  # the most confident point of each voxel wins
    assert len(voxel_downsample_by_confidence(pts, conf, 10_000)) == 5000


def test_pixel_downsample_keeps_the_best_point_per_cell_and_meets_the_budget():
    from mvgeo.align.scene import best_per_pixel_cell, best_per_pixel_cell_reference, pixel_downsample_by_confidence

    rng = np.random.default_rng(3)
    P = 5000
    view, row, col = rng.integers(0, 3, P), rng.integers(0, 48, P), rng.integers(0, 64, P)
    conf = np.round(rng.uniform(1.0, 11.0, P), 1)  # rounded: ties occur and must go to the lower index
    for size in (1.0, 2.5, 7.0, 64.0):
        np.testing.assert_array_equal(best_per_pixel_cell(view, row, col, conf, size),
                                      best_per_pixel_cell_reference(view, row, col, conf, size))
    n_pixels = len(np.unique(np.stack([view, row, col], 1), axis=0))
    for budget in (1, 2, 3, 50, 700, 4999, 5000):
        sel = pixel_downsample_by_confidence(view, row, col, conf, budget)
        assert len(sel) <= budget and len(np.unique(sel)) == len(sel)
        if 3 <= budget < P:  # a cell partition: near the budget (bisection to 1 % in size), never over
            assert len(sel) >= 0.9 * min(budget, n_pixels), (budget, len(sel))
    top = pixel_downsample_by_confidence(view, row, col, conf, 2)  # fewer points than views
    assert set(conf[top]) <= set(np.sort(conf)[-50:])  # each is its view's best: among the top scores


def _covisibility_reference(pts, depth, conf, cams, Ks, rel_tol, cons_tol, free_tol, measured=None):
    """`covisibility_keep`'s docstring, pixel by pixel (slow, obvious)."""
    keep = []
    for a in range(len(pts)):
        H, W = depth[a].shape
        k = np.ones((H, W), bool)
        for r in range(H):
            for c in range(W):
                drop, confirmed, seen = False, False, False
                for b in range(len(pts)):
                    if b == a:
                        continue
                    x = cams[b][:, :3] @ pts[a][r, c] + cams[b][:, 3]
                    if not x[2] > 0:
                        continue
                    u = Ks[b][0, 0] * x[0] / x[2] + Ks[b][0, 2]
                    v = Ks[b][1, 1] * x[1] / x[2] + Ks[b][1, 2]
                    Hb, Wb = depth[b].shape
                    if not (0 <= u < Wb and 0 <= v < Hb):
                        continue
                    db, cb = depth[b][int(np.floor(v)), int(np.floor(u))], conf[b][int(np.floor(v)), int(np.floor(u))]
                    if abs(x[2] - db) < rel_tol * db and (cb > conf[a][r, c] or (cb == conf[a][r, c] and b < a)):
                        drop = True
                    if (measured is not None and measured[a][r, c]
                            and not measured[b][int(np.floor(v)), int(np.floor(u))]):
                        continue  # a filled pixel: no evidence against a measured point in the checks below
                    if cons_tol > 0:
                        confirmed |= bool(abs(x[2] - db) < cons_tol * db)
                        seen |= bool(np.isfinite(db) and db > 0)
                    if free_tol > 0 and x[2] < (1.0 - free_tol) * db:
                        drop = True
                k[r, c] = not (drop or (seen and not confirmed))
        keep.append(k)
    return keep


@pytest.mark.parametrize("workers, chunk", [(1, None), (3, None), (1, 7), (3, 50)])
def test_covisibility_matches_the_pixel_loop_with_any_number_of_threads(rng, monkeypatch, workers, chunk):
    """Four views of a bumpy surface from nearby cameras, ties in confidence included: the vectorised,
    threaded masks equal the pixel-by-pixel reference, for one thread or several, and with each view's points
    taken in chunks (7 and 50 of its 108 points; None: the default, the whole view at once here)."""
    import mvgeo.align.scene as scene
    from mvgeo.transforms import R_from_axis_angle

    if chunk is not None:
        monkeypatch.setattr(scene, "_CHUNK", chunk)

    H, W, f = 9, 12, 10.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    cams, pts, depth, conf = [], [], [], []
    for _ in range(4):
        R = R_from_axis_angle(rng.normal(0, 0.05, 3))
        t = rng.normal(0, 0.1, 3)
        cams.append(np.concatenate([R, t[:, None]], 1))
        d = 2.0 + 0.1 * rng.standard_normal((H, W))
        d[rng.random((H, W)) < 0.1] = np.nan  # missing depth, as hole-free stereo leaves
        x_cam = pixel_rays(H, W, f) * d[..., None]
        pts.append((x_cam - t) @ R)  # R^T (x - t)
        depth.append(d)
        conf.append(rng.integers(1, 4, (H, W)).astype(float))  # small integers: ties happen
    cams = np.stack(cams)
    args = (pts, depth, conf, cams, [K] * 4)
    measured = [rng.random((H, W)) < 0.7 for _ in range(4)]  # the other pixels' depths count as filled
    for tols, meas in [((0.03, 0.0, 0.0), None), ((0.03, 0.05, 0.05), None), ((0.03, 0.05, 0.05), measured)]:
        got = covisibility_keep(*args, rel_depth_tol=tols[0], consistency_rel_tol=tols[1],
                                free_space_rel_tol=tols[2], measured=meas, workers=workers)
        want = _covisibility_reference(*args, *tols, measured=meas)
        assert all(np.array_equal(g, w) for g, w in zip(got, want, strict=True))
        assert 0 < sum(int(g.sum()) for g in got) < 4 * H * W  # some dropped, some kept: the test can fail
    # The filled pixels' evidence is ignored, not every pixel's: the masks differ from the run without it.
    unmasked = covisibility_keep(*args, rel_depth_tol=0.03, consistency_rel_tol=0.05, free_space_rel_tol=0.05)
    assert any(not np.array_equal(g, w) for g, w in zip(got, unmasked, strict=True))

"""Fast paths of the pair stage against obvious references: matching, dense-pair selection, consistency."""

import numpy as np

from mvgeo.align.checks import pair_consistency
from mvgeo.align.classical_pairs import (
    ImageFeatures,
    match_features,
    match_features_reference,
    select_dense_pairs,
)
from mvgeo.align.graph import components
from mvgeo.transforms import so3_exp


def test_blas_matching_equals_loop_reference(rng):
    base = rng.random((300, 128)).astype(np.float32) * 100
    a = ImageFeatures(np.zeros((300, 2)), base)
    # 200 noisy copies (true matches), 40 near-duplicates of one descriptor (ambiguous: ratio test
    # must reject), 60 unrelated.
    b_desc = np.concatenate([base[:200] + rng.random((200, 128)).astype(np.float32) * 15,
                             np.repeat(base[250:251], 40, axis=0) + rng.random((40, 128)).astype(np.float32),
                             rng.random((60, 128)).astype(np.float32) * 100])
    b = ImageFeatures(np.zeros((300, 2)), b_desc)
    for ratio in (0.6, 0.8, 0.95):
        fast = match_features(a, b, ratio=ratio)
        ref = match_features_reference(a, b, ratio=ratio)
        np.testing.assert_array_equal(fast, ref)
    assert 150 < len(match_features(a, b, ratio=0.8)) <= 200
    # Row blocks of any size (incl. one row, and blocks that do not divide the rows) give the same matches.
    for block in (1, 7, 64, 1000):
        np.testing.assert_array_equal(match_features(a, b, ratio=0.8, block_rows=block),
                                      match_features_reference(a, b, ratio=0.8))
    # Exact ties: two identical rows in a both best match one column; the column's ratio test must
    # reject both (as the loop does), not match that column twice.
    a_tie = ImageFeatures(np.zeros((301, 2)), np.concatenate([base, base[:1]]))
    fast = match_features(a_tie, b, ratio=0.95, block_rows=7)
    np.testing.assert_array_equal(fast, match_features_reference(a_tie, b, ratio=0.95))
    assert 0 not in fast[:, 0] and 300 not in fast[:, 0] and 0 in match_features(a, b, ratio=0.95)[:, 0]
    assert len(match_features(a, ImageFeatures(np.zeros((1, 2)), b_desc[:1]), ratio=0.8)) == 0


def test_dense_pair_selection_is_connected_and_top_k(rng):
    n = 10
    inliers = {(i, j): int(rng.integers(20, 500)) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.6}
    inliers.update({(i, i + 1): 25 for i in range(n - 1)})  # a weak chain keeps the full graph connected
    for k in (1, 2, 4):
        sel = select_dense_pairs(n, inliers, k)
        assert len(components(n, sel)) == 1
        for v in range(n):
            mine = sorted((p for p in inliers if v in p), key=lambda p: -inliers[p])[:k]
            assert set(mine) <= set(sel)
    assert sorted(select_dense_pairs(n, inliers, 0)) == sorted(inliers)


def test_pair_consistency_exact_and_wrong_geometry(rng):
    W, H, f = 320, 240, 300.0
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (80, 3))
    poses = np.stack([np.concatenate([so3_exp(np.array([0, 0.1 * k, 0])), np.array([[-0.5 * k], [0], [0]])], 1)
                      for k in range(3)])
    uv = []
    for P in poses:
        xc = X @ P[:, :3].T + P[:, 3]
        uv.append(f * xc[:, :2] / xc[:, 2:] + [W / 2, H / 2])
    matches = [(i, j, np.concatenate([uv[i], uv[j]], 1)) for i, j in ((0, 1), (0, 2), (1, 2))]
    good = pair_consistency(poses, np.full(3, f), (W, H), matches)
    assert all(c.explained_fraction == 1.0 and c.n_matches == 80 for c in good)
    wrong = poses.copy()
    wrong[2, :, :3] = so3_exp(np.array([0.0, 0.0, 0.3])) @ wrong[2, :, :3]  # view 2 rolled by 17 deg
    bad = {(c.i, c.j): c.explained_fraction for c in pair_consistency(wrong, np.full(3, f), (W, H), matches)}
    assert bad[(0, 1)] == 1.0 and bad[(0, 2)] < 0.5 and bad[(1, 2)] < 0.5


def test_pointmap_triangulates_only_checked_pixels_same_result(rng):
    """`_pointmap` (triangulates the pixels that pass the flow/epipolar checks) vs triangulating all."""
    from mvgeo.align.classical_pairs import ClassicalPointmapModel
    from mvgeo.transforms import skew

    from .synthetic import look_at, render_depth

    H, W, f = 48, 64, 60.0
    Ta = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 4.0]))
    Tb = look_at(np.array([0.6, 0.1, 0.0]), np.array([0.0, 0.0, 4.0]))
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    Tba = np.c_[Tb[:, :3] @ Ta[:, :3].T, Tb[:, 3] - Tb[:, :3] @ Ta[:, :3].T @ Ta[:, 3]]

    def flow(Tsrc, Tdst):
        d = render_depth(Tsrc, H, W, f)
        v, u = np.mgrid[0:H, 0:W] + 0.5
        X = np.stack([(u - W / 2) / f * d, (v - H / 2) / f * d, d], -1) @ Tsrc[:, :3]  # R^T x
        X = X - Tsrc[:, :3].T @ Tsrc[:, 3]
        Y = X @ Tdst[:, :3].T + Tdst[:, 3]
        uv = Y[..., :2] / Y[..., 2:] * f + [W / 2, H / 2]
        return (uv - np.stack([u, v], -1)).astype(np.float32)

    fab, fba = flow(Ta, Tb), flow(Tb, Ta)
    fab += rng.normal(scale=0.4, size=fab.shape).astype(np.float32)  # some pixels fail the checks
    R, t = Tba[:, :3], Tba[:, 3]
    F = np.linalg.inv(K).T @ skew(t) @ R @ np.linalg.inv(K)
    model = ClassicalPointmapModel()
    pts, conf = model._pointmap(fab, fba, K, K, F, Tba)
    pts_ref, conf_ref = model._pointmap_reference(fab, fba, K, K, F, Tba)
    assert 0.2 < np.mean(conf > 1) < 0.95  # both kept and rejected pixels are exercised
    np.testing.assert_array_equal(conf > 1, conf_ref > 1)
    # Row-wise identical arithmetic; only BLAS's blocking of the (N, 3) products may differ: 1e-12.
    np.testing.assert_allclose(conf, conf_ref, rtol=1e-12)
    np.testing.assert_allclose(pts, pts_ref, rtol=1e-12, atol=1e-12)
    none = model._pointmap(fab + 50.0, fba, K, K, F, Tba)  # every target outside: placeholder rays only
    np.testing.assert_allclose(none[0], model._pointmap_reference(fab + 50.0, fba, K, K, F, Tba)[0])
    assert np.all(none[1] == 1)

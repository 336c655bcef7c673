"""Pose metrics: invariances, known answers, and brute-force references."""

import numpy as np
import pytest

from mvgeo import metrics as mt
from mvgeo import transforms as tf
from mvgeo.common.errors import DegenerateGeometryError


def random_poses(rng, n):
    w = rng.normal(size=(n, 3))
    return tf.se3_exp(np.concatenate([w / np.linalg.norm(w, axis=1, keepdims=True) * rng.uniform(0, 3, (n, 1)),
                                      rng.normal(size=(n, 3))], 1))


def test_rotation_error_known_angles_and_small_angle_accuracy(rng):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = np.array([1e-10, 1e-6, 0.1, 1.0, np.pi - 1e-9, np.pi])
    R = tf.so3_exp(axis * ang[:, None])
    # atan2 form: relative accuracy ~1e-15 even at 1e-10 rad (arccos would give 0 or 1e-8).
    np.testing.assert_allclose(mt.rotation_error_deg(R, np.eye(3)), np.degrees(ang), rtol=1e-9)
    B = tf.so3_exp(rng.normal(size=(100, 3)))
    np.testing.assert_allclose(mt.rotation_error_deg(B @ R[2], B), np.degrees(0.1), rtol=1e-12)


def test_translation_direction_error():
    e = mt.translation_direction_error_deg([[1, 0, 0], [1, 0, 0], [1, 0, 0], [0, 0, 0]],
                                           [[2, 0, 0], [0, 3, 0], [-1, 0, 0], [1, 0, 0]])
    np.testing.assert_allclose(e[:3], [0, 90, 180], atol=1e-12)
    assert np.isnan(e[3])


def test_relative_errors_invariant_to_similarity_and_exact_for_perturbation(rng):
    ref = random_poses(rng, 6)
    world_from_new = tf.sim3_exp(np.r_[rng.normal(size=6), 0.7])
    # The same cameras in another world frame and scale: cam_from_new = cam_from_world @ world_from_new,
    # with the scale moved into the translation (rigid cam_from_world up to scale).
    s = np.exp(0.7)
    est = np.stack([tf.compose(T, world_from_new) for T in ref])
    est[:, :3, :3] /= s
    rel = mt.relative_pose_errors(est, ref)
    assert rel.pairs.shape == (15, 2)
    # Invariance holds to rounding: 1e-5 degrees.
    assert rel.rotation_deg.max() < 1e-5 and np.nanmax(rel.translation_deg) < 1e-5
    # Rotate camera 0 by 3 degrees about its own centre: all pairs with camera 0 show exactly 3 deg.
    bad = ref.copy()
    C0 = tf.camera_centre(ref[0])
    R_new = tf.so3_exp([0, np.radians(3), 0]) @ ref[0, :3, :3]
    bad[0] = tf.matrix_from_Rt(R_new, -R_new @ C0)
    rel = mt.relative_pose_errors(bad, ref)
    with0 = rel.pairs[:, 0] == 0
    np.testing.assert_allclose(rel.rotation_deg[with0], 3.0, rtol=1e-9)
    assert rel.rotation_deg[~with0].max() < 1e-9


def test_ate_recovers_sim3_and_reports_error(rng):
    ref_c = rng.normal(size=(10, 3))
    sim = tf.sim3_exp(np.r_[rng.normal(size=6), -0.5])
    est_c = tf.apply(tf.invert(sim), ref_c)
    res = mt.ate(est_c, ref_c)
    assert res.rmse < 1e-12
    np.testing.assert_allclose(res.ref_from_est.matrix, sim, atol=1e-12)
    noisy = est_c.copy()
    noisy[3] += 0.1
    res = mt.ate(noisy, ref_c)
    assert 0 < res.rmse < 0.2 and res.errors.shape == (10,) and res.max == res.errors.max()


def test_rpe_zero_for_scaled_estimate_and_known_error(rng):
    ref = random_poses(rng, 5)
    est = ref.copy()
    est[:, :3, 3] *= 0.5
    r = mt.rpe(est, ref, scale=2.0)
    assert r.translation_rmse < 1e-12 and r.rotation_rmse_deg < 1e-9
    est = ref.copy()
    est[2, :3, 3] += [0.3, 0.0, 0.0]
    r = mt.rpe(est, ref)
    assert r.translation_errors.shape == (4,)
    # Only motions involving frame 2 (pairs 1-2 and 2-3) are wrong, each by 0.3 in translation.
    np.testing.assert_allclose(r.translation_errors, [0, 0.3, 0.3, 0], atol=1e-12)
    with pytest.raises(DegenerateGeometryError):
        mt.rpe(est, ref, delta=5)


def test_pose_auc_against_fine_numeric_integration(rng):
    e = np.concatenate([rng.exponential(8.0, 200), [np.inf, np.nan]])
    auc = mt.pose_auc(e, thresholds=(5, 10, 20))
    for thr, val in auc.items():
        # Slow reference: recall is linearly interpolated between sorted errors; integrate on a fine grid.
        s = np.sort(np.where(np.isfinite(e), e, np.inf))
        xs = np.concatenate([[0.0], s[np.isfinite(s)]])
        ys = np.arange(xs.size) / e.size
        grid = np.linspace(0, thr, 200001)
        ref = np.mean(np.interp(grid, xs, ys))
        # Grid step 1e-4 deg: rectangle-rule error < 1e-4 relative.
        assert abs(val - ref) < 1e-4
    assert mt.pose_auc([0.0, 0.0])[5.0] == 1.0
    assert mt.pose_auc([np.inf])[5.0] == 0.0
    assert mt.accuracy_at([1, 6, 11, np.nan]) == {5.0: 0.25, 10.0: 0.5, 20.0: 0.75}


def test_compare_poses_registration_and_perfect_match(rng):
    ref_T = random_poses(rng, 6)
    names = [f"img{i:02d}.png" for i in range(6)]
    ref = dict(zip(names, ref_T, strict=True))
    world_from_new = tf.se3_exp(rng.normal(size=6))
    est = {n: tf.compose(T, world_from_new)[:3] * np.r_[1, 1, 1, 3.0] for n, T in ref.items()}
    est["extra.png"] = np.eye(4)
    m = mt.compare_poses(est, ref)
    assert m.registered_fraction == 1.0 and m.n_pairs_total == 15
    assert m.rra[5.0] == 1.0 and m.rta[5.0] == 1.0 and m.auc[5.0] > 0.999
    assert m.ate is not None and m.ate.rmse < 1e-10
    del est[names[0]], est[names[1]]
    m = mt.compare_poses(est, ref)
    assert m.n_registered == 4 and m.registered_fraction == pytest.approx(4 / 6)
    # 6 of 15 pairs remain measured; unregistered pairs count as failures.
    assert m.rotation_deg.shape == (6,)
    assert m.rra[5.0] == pytest.approx(6 / 15)
    assert set(m.summary()) >= {"rra@5", "rta@10", "auc@20", "ate_rmse", "registered_fraction"}
    with pytest.raises(DegenerateGeometryError):
        mt.compare_poses(est, {names[0]: ref_T[0]})


def test_ate_is_undetermined_when_the_reference_centres_coincide(rng):
    # Cameras turning about one centre (pure rotation): Umeyama's scale is 0 and every estimated centre lands on
    # that point, an ATE of 0 for any estimate. It is reported as undetermined instead.
    from scipy.spatial.transform import Rotation

    from mvgeo.metrics import ate, compare_poses

    est = rng.normal(size=(6, 3))
    with pytest.raises(DegenerateGeometryError, match="reference centres coincide"):
        ate(est, np.zeros((6, 3)))
    assert ate(est, np.zeros((6, 3)), with_scale=False).rmse > 0  # SE(3): the estimate's spread is its error
    ref = {f"{i}": np.hstack([Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix(), np.zeros((3, 1))])
           for i in range(6)}
    moved = {k: np.hstack([v[:, :3], rng.normal(size=(3, 1))]) for k, v in ref.items()}
    m = compare_poses(moved, ref)
    assert m.ate is None and np.isnan(m.summary()["ate_rmse"])


def test_ate_value_against_a_direct_least_squares_fit(rng):
    # A non-zero ATE checked against its definition: the RMSE of the centres after the Sim(3) that minimises it,
    # found here by scipy's least squares over (rotation vector, translation, log scale) from several starts.
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    ref = rng.normal(size=(12, 3))
    est = 0.4 * ref @ Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix().T + [1.0, 2.0, -0.5]
    est += rng.normal(0, 0.05, est.shape)

    def resid(p):
        return (np.exp(p[6]) * est @ Rotation.from_rotvec(p[:3]).as_matrix().T + p[3:6] - ref).ravel()

    best = min((least_squares(resid, np.r_[Rotation.random(random_state=k).as_rotvec(), 0, 0, 0, 0.0], xtol=1e-15,
                              ftol=1e-15, gtol=1e-15) for k in range(5)), key=lambda r: r.cost)
    err = np.linalg.norm(best.fun.reshape(-1, 3), axis=1)
    res = mt.ate(est, ref)
    assert res.rmse > 0.05  # not a near-zero case
    assert res.rmse == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-6)
    assert res.mean == pytest.approx(err.mean(), rel=1e-5)
    assert res.median == pytest.approx(np.median(err), rel=1e-5)
    assert res.max == pytest.approx(err.max(), rel=1e-5)


def test_compare_poses_pair_errors_and_medians_against_a_loop(rng):
    from scipy.spatial.transform import Rotation

    ref = {f"v{i}": np.hstack([Rotation.random(random_state=i).as_matrix(), rng.normal(size=(3, 1))])
           for i in range(7)}
    est = {}
    for k, (name, P) in enumerate(ref.items()):  # each view turned and moved by its own amount, the last by 40 deg
        d = Rotation.from_rotvec(rng.normal(0, np.radians(1.0 + 0.3 * k), 3)).as_matrix()
        if k == 6:
            d = Rotation.from_rotvec(np.radians(40.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
        est[name] = np.hstack([d @ P[:, :3], 2.0 * P[:, 3:] + rng.normal(0, 0.05, (3, 1))])
    names = list(ref)
    rot, tra = [], []
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            def rel(P, Q):  # cam_a_from_cam_b, the documented relative pose (`RelativePoseErrors`)
                R = P[:, :3] @ Q[:, :3].T
                return R, P[:, 3] - R @ Q[:, 3]
            Rr, tr = rel(ref[names[a]], ref[names[b]])
            Re, te = rel(est[names[a]], est[names[b]])
            rot.append(np.degrees(Rotation.from_matrix(Re @ Rr.T).magnitude()))
            c = te @ tr / (np.linalg.norm(te) * np.linalg.norm(tr))
            tra.append(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    m = mt.compare_poses(est, ref)
    np.testing.assert_allclose(np.sort(m.rotation_deg), np.sort(rot), atol=1e-9)
    np.testing.assert_allclose(np.sort(m.translation_deg), np.sort(tra), atol=1e-7)
    assert m.median_rotation_deg == pytest.approx(np.median(rot), abs=1e-9)
    assert m.median_translation_deg == pytest.approx(np.median(tra), abs=1e-7)
    assert np.median(rot) < 0.9 * np.mean(rot) or np.median(rot) > 1.1 * np.mean(rot)  # a median, not a mean
    worse = np.maximum(rot, tra)  # the AUC is of the worse of the two errors of each pair
    for thr, value in m.auc.items():
        assert value == pytest.approx(mt.pose_auc(worse, thresholds=(thr,))[thr], abs=1e-12)


def test_rpe_rmse_values_against_a_loop(rng):
    from scipy.spatial.transform import Rotation

    ref = random_poses(rng, 6)
    est = ref.copy()
    for k in range(6):
        est[k, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix() @ est[k, :3, :3]
        est[k, :3, 3] += rng.normal(0, 0.1, 3)
    r = mt.rpe(est, ref, delta=2)
    t_err, r_err = [], []
    for k in range(4):
        def motion(P, Q):  # cam_k_from_cam_{k+2} as 4x4
            A, B = np.eye(4), np.eye(4)
            A[:3], B[:3] = P[:3], Q[:3]
            return A @ np.linalg.inv(B)
        E = np.linalg.inv(motion(ref[k], ref[k + 2])) @ motion(est[k], est[k + 2])
        t_err.append(np.linalg.norm(E[:3, 3]))
        r_err.append(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()))
    assert r.translation_rmse == pytest.approx(np.sqrt(np.mean(np.square(t_err))), rel=1e-9)
    assert r.rotation_rmse_deg == pytest.approx(np.sqrt(np.mean(np.square(r_err))), rel=1e-7)

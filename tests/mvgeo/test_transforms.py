"""mvgeo.transforms against scipy, scipy.linalg.expm/logm, pycolmap and brute-force references."""

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from mvgeo import transforms as tf
from mvgeo.common.deps import pycolmap
from mvgeo.common.errors import DegenerateGeometryError, ShapeError


def random_axis_angle(rng, n, *, lo=0.0, hi=np.pi, log=False):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = 10 ** rng.uniform(np.log10(lo), np.log10(hi), n) if log else rng.uniform(lo, hi, n)
    return axis * ang[:, None]


def hat4(xi):
    X = np.zeros((4, 4))
    X[:3, :3] = tf.skew(xi[:3])
    X[:3, 3] = xi[3:6]
    if xi.shape[0] == 7:
        X[:3, :3] += xi[6] * np.eye(3)
    return X


def test_quaternions_match_scipy_either_sign(rng):
    q = rng.normal(size=(500, 4))
    R = tf.R_from_quat(q)
    # Tolerance 1e-14: both are closed-form polynomial expressions of the normalised quaternion.
    np.testing.assert_allclose(R, Rotation.from_quat(q, scalar_first=True).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(tf.R_from_quat(-q), R, atol=1e-15)
    q_back = tf.quat_from_R(R)
    assert np.all(q_back[:, 0] >= 0)
    expected = q / np.linalg.norm(q, axis=1, keepdims=True) * np.sign(q[:, :1])
    np.testing.assert_allclose(q_back, expected, atol=1e-14)


def test_quat_from_R_near_pi_uses_stable_pivot(rng):
    omega = random_axis_angle(rng, 300, lo=np.pi - 1e-6, hi=np.pi)
    R = tf.so3_exp(omega)
    q = tf.quat_from_R(R)
    # At angle pi - 1e-6, w ~ 5e-7: the w-pivot formula would divide by it; Shepperd does not.
    np.testing.assert_allclose(tf.R_from_quat(q), R, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)


def test_so3_exp_log_match_scipy_over_all_angle_scales(rng):
    omega = random_axis_angle(rng, 1000, lo=1e-12, hi=np.pi - 1e-9, log=True)
    R = tf.so3_exp(omega)
    np.testing.assert_allclose(R, Rotation.from_rotvec(omega).as_matrix(), atol=2e-15)
    # log(exp(w)) = w for angle < pi; relative accuracy ~1e-15 even at 1e-12 rad thanks to the series.
    back = tf.so3_log(R)
    np.testing.assert_allclose(back, omega, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(back, Rotation.from_matrix(R).as_rotvec(), rtol=1e-9, atol=1e-15)
    assert tf.R_from_axis_angle is tf.so3_exp and tf.axis_angle_from_R is tf.so3_log


@pytest.mark.parametrize("angle", [0.0, 1e-6, 1e-3, 0.3, 2.5])
def test_so3_left_jacobian_against_central_differences_and_se3_block(rng, angle):
    """``d/dd exp(omega + d) exp(omega)^T`` at d = 0 is ``[J_l e_k]_x`` for each axis k (central differences,
    h = 1e-6: error O(h^2) ~ 1e-12, far inside 1e-8); J_l is also se3_exp's translation block V."""
    axis = rng.normal(size=3)
    omega = angle * axis / np.linalg.norm(axis)
    J = tf.so3_left_jacobian(omega)
    h = 1e-6
    R0 = tf.so3_exp(omega)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        dR = (tf.so3_exp(omega + e) - tf.so3_exp(omega - e)) @ R0.T / (2 * h)
        np.testing.assert_allclose(dR, tf.skew(J[:, k]), atol=1e-8)
    v = rng.normal(size=3)
    np.testing.assert_allclose(tf.se3_exp(np.concatenate([omega, v]))[:3, 3], J @ v, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1e-4, 1e-3, 0.3, 0.49999, 0.5, 0.50001, 2.5, np.pi])
def test_so3_exp_and_left_jacobian_equal_the_array_versions(rng, angle):
    """The scalar path (`so3_exp_and_left_jacobian`, used in the two-view refinement's inner loop) equals
    `so3_exp` and `so3_left_jacobian` on either side of both series switches (1e-4 and 0.5 rad): the same
    formulas, so only rounding separates them (1e-15)."""
    axis = rng.normal(size=3)
    omega = angle * axis / np.linalg.norm(axis)
    R, J = tf.so3_exp_and_left_jacobian(omega)
    np.testing.assert_allclose(R, tf.so3_exp(omega), rtol=0, atol=1e-15)
    np.testing.assert_allclose(J, tf.so3_left_jacobian(omega), rtol=0, atol=1e-15)


def test_so3_log_exactly_pi_and_identity():
    for axis in np.eye(3):
        R = tf.so3_exp(np.pi * axis)
        w = tf.so3_log(R)
        # Either sign is the same rotation at pi; the canonical one is returned.
        np.testing.assert_allclose(np.abs(w), np.pi * axis, atol=1e-15)
        np.testing.assert_allclose(tf.so3_exp(w), R, atol=1e-15)
    assert np.array_equal(tf.so3_log(np.eye(3)), np.zeros(3))


def test_se3_sim3_exp_against_matrix_exponential(rng):
    # scipy.linalg.expm of the 4x4 Lie-algebra matrix is the slow, obvious reference.
    for _ in range(40):
        w = random_axis_angle(rng, 1, lo=1e-9, hi=np.pi, log=True)[0]
        xi = np.concatenate([w, rng.normal(size=3)])
        # Tolerance 1e-13: expm's Pade scaling-and-squaring is accurate to ~1e-15 relative.
        np.testing.assert_allclose(tf.se3_exp(xi), expm(hat4(xi)), atol=1e-13)
        xs = np.concatenate([xi, rng.normal(size=1)])
        np.testing.assert_allclose(tf.sim3_exp(xs), expm(hat4(xs)), atol=1e-12)


def test_se3_sim3_log_roundtrip_batched(rng):
    w = random_axis_angle(rng, 600, lo=1e-10, hi=np.pi - 1e-6, log=True)
    xi = np.concatenate([w, rng.normal(size=(600, 3))], axis=1).reshape(20, 30, 6)
    T = tf.se3_exp(xi)
    assert T.shape == (20, 30, 4, 4)
    # 1e-12: the log goes through atan2 and a cancellation-free V^-1 (series below 0.5 rad).
    np.testing.assert_allclose(tf.se3_log(T), xi, atol=1e-12)
    np.testing.assert_allclose(tf.se3_log(T[..., :3, :]), xi, atol=1e-12)
    xs = np.concatenate([xi, rng.normal(size=(20, 30, 1))], axis=-1)
    np.testing.assert_allclose(tf.sim3_log(tf.sim3_exp(xs)), xs, atol=1e-11)


def test_compose_invert_apply(rng):
    A = tf.se3_exp(np.concatenate([random_axis_angle(rng, 50), rng.normal(size=(50, 3))], 1))
    B = tf.sim3_exp(np.concatenate([random_axis_angle(rng, 50), rng.normal(size=(50, 4))], 1))
    np.testing.assert_allclose(tf.compose(A, B), A @ B, atol=1e-13)
    np.testing.assert_allclose(tf.invert(B), np.linalg.inv(B), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(tf.invert(A[:, :3]), np.linalg.inv(A)[:, :3], atol=1e-13)
    assert tf.compose(A[:, :3], B[:, :3]).shape == (50, 3, 4)
    assert tf.compose(A[:, :3], B).shape == (50, 4, 4)
    p = rng.normal(size=(50, 7, 3))
    ph = np.concatenate([p, np.ones((50, 7, 1))], -1)
    np.testing.assert_allclose(tf.apply(B, p), (ph @ np.swapaxes(B, -1, -2))[..., :3], atol=1e-12)
    # Non-contiguous input and broadcasting of one transform over a batch of point sets.
    np.testing.assert_allclose(tf.apply(A[0], p[:, ::2]), p[:, ::2] @ A[0, :3, :3].T + A[0, :3, 3], atol=1e-13)
    C = tf.camera_centre(A)
    np.testing.assert_allclose(tf.apply(A, C[:, None])[:, 0], 0.0, atol=1e-12)
    with pytest.raises(ShapeError):
        tf.apply(A, p[..., :2])


def test_pycolmap_rigid3d_interop(rng):
    q = tf.quat_from_R(tf.so3_exp(random_axis_angle(rng, 1)[0]))
    t = rng.normal(size=3)
    # pycolmap Rotation3d takes / returns xyzw (Eigen order): convert at the boundary.
    rig = pycolmap.Rigid3d(pycolmap.Rotation3d(np.r_[q[1:], q[0]]), t)
    np.testing.assert_allclose(rig.matrix(), tf.matrix_from_Rt(tf.R_from_quat(q), t, homogeneous=False), atol=1e-14)
    xyzw = rig.rotation.quat
    np.testing.assert_allclose(tf.quat_from_R(rig.rotation.matrix()), np.r_[xyzw[3], xyzw[:3]] * np.sign(xyzw[3]),
                               atol=1e-14)
    np.testing.assert_allclose(rig.inverse().matrix(), tf.invert(rig.matrix()), atol=1e-14)


def test_umeyama_recovers_similarity_with_weights_and_outliers(rng):
    for _ in range(30):
        src = rng.normal(size=(40, 3))
        s = float(np.exp(rng.normal()))
        R = tf.so3_exp(random_axis_angle(rng, 1)[0])
        t = rng.normal(size=3)
        dst = s * src @ R.T + t
        fit = tf.umeyama(src, dst)
        # Exact data: recovered to rounding (1e-12).
        np.testing.assert_allclose([fit.scale], [s], rtol=1e-12)
        np.testing.assert_allclose(fit.R, R, atol=1e-12)
        np.testing.assert_allclose(fit.t, t, atol=1e-11)
        assert fit.well_posed and fit.rmse < 1e-12
        np.testing.assert_allclose(fit.apply(src), dst, atol=1e-11)
        np.testing.assert_allclose(tf.apply(fit.matrix, src), dst, atol=1e-11)
        # Zero weight removes gross outliers exactly.
        bad = dst.copy()
        bad[:5] += 100
        w = np.ones(40)
        w[:5] = 0
        fit_w = tf.umeyama(src, bad, weights=w)
        np.testing.assert_allclose(fit_w.R, R, atol=1e-11)
        rigid = tf.umeyama(src, src @ R.T + t, with_scale=False)
        assert rigid.scale == 1.0
        np.testing.assert_allclose(rigid.R, R, atol=1e-12)


def test_umeyama_weighted_matches_brute_force_optimum(rng):
    # Noisy weighted fit: the closed form must beat every perturbation of itself (local optimality).
    src = rng.normal(size=(25, 3))
    dst = 2.0 * src @ tf.so3_exp([0.3, -0.2, 0.1]).T + 1.0 + 0.05 * rng.normal(size=(25, 3))
    w = rng.uniform(0.1, 2.0, 25)
    fit = tf.umeyama(src, dst, weights=w)

    def cost(scale, R, t):
        return np.sum(w * np.sum((dst - scale * src @ R.T - t) ** 2, axis=1))

    c0 = cost(fit.scale, fit.R, fit.t)
    for _ in range(200):
        d = rng.normal(scale=1e-3, size=7)
        assert cost(fit.scale * np.exp(d[6]), tf.so3_exp(d[:3]) @ fit.R, fit.t + d[3:6]) >= c0 - 1e-12


def test_average_rotations_chordal(rng):
    R0 = tf.so3_exp(random_axis_angle(rng, 1)[0])
    noise = tf.so3_exp(random_axis_angle(rng, 200, hi=0.05))
    Rs = noise @ R0
    avg = tf.average_rotations_chordal(Rs)
    np.testing.assert_allclose(avg @ avg.T, np.eye(3), atol=1e-14)
    # Chordal L2 mean equals scipy's Rotation.mean (same definition, via quaternion eigenvector).
    ref = Rotation.from_matrix(Rs).mean().as_matrix()
    assert np.degrees(np.linalg.norm(tf.so3_log(avg.T @ ref))) < 1e-6
    assert np.degrees(np.linalg.norm(tf.so3_log(avg.T @ R0))) < 0.5
    w = np.zeros(200)
    w[7] = 1.0
    np.testing.assert_allclose(tf.average_rotations_chordal(Rs, weights=w), Rs[7], atol=1e-14)
    with pytest.raises(DegenerateGeometryError):
        tf.average_rotations_chordal(Rs[:0])

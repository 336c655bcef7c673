"""Torch twins: values against the numpy float64 reference, float64 gradcheck, finite gradients at 0 and pi."""

import numpy as np
import pytest
import torch

from mvgeo import transforms as tf
from mvgeo import transforms_torch as tt
from mvgeo.common.errors import ShapeError


def _omegas(rng, n, lo, hi):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * (10 ** rng.uniform(np.log10(lo), np.log10(hi), n))[:, None]


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_values_match_numpy_reference_with_batch_dims(rng, batch):
    n = int(np.prod(batch, dtype=int))
    w = _omegas(rng, max(n, 1), 1e-10, np.pi - 1e-7)[:n].reshape(batch + (3,))
    xi = np.concatenate([w, rng.normal(size=batch + (3,))], -1)
    q = rng.normal(size=batch + (4,))
    T = torch.from_numpy
    # float64 twins agree with numpy to rounding (1e-13).
    np.testing.assert_allclose(tt.so3_exp(T(w)).numpy(), tf.so3_exp(w), atol=1e-13)
    np.testing.assert_allclose(tt.se3_exp(T(xi)).numpy(), tf.se3_exp(xi), atol=1e-13)
    np.testing.assert_allclose(tt.se3_log(T(tf.se3_exp(xi))).numpy(), xi, atol=1e-11)
    np.testing.assert_allclose(tt.so3_log(T(tf.so3_exp(w))).numpy(), w, atol=1e-12)
    np.testing.assert_allclose(tt.R_from_quat(T(q)).numpy(), tf.R_from_quat(q), atol=1e-14)
    np.testing.assert_allclose(tt.quat_from_R(T(tf.R_from_quat(q))).numpy(), tf.quat_from_R(tf.R_from_quat(q)),
                               atol=1e-13)


def test_float32_and_left_multiplied_pose_update(rng):
    xi = torch.tensor(rng.normal(scale=0.1, size=(8, 6)), dtype=torch.float32)
    cam_from_world = tt.se3_exp(torch.tensor(rng.normal(size=(8, 6)), dtype=torch.float32))
    new = tt.se3_exp(xi) @ cam_from_world
    assert new.dtype == torch.float32 and new.shape == (8, 4, 4)
    ref = tf.se3_exp(xi.double().numpy()) @ cam_from_world.double().numpy()
    # float32: ~1e-6 relative per op, a few ops deep.
    np.testing.assert_allclose(new.numpy(), ref, atol=2e-5)


def test_gradcheck_float64_generic_small_and_near_pi(rng):
    cases = [
        _omegas(rng, 2, 0.5, 3.0),  # generic
        _omegas(rng, 2, 1e-7, 1e-3),  # Taylor branches (exp uses series below 0.5 / 1e-4 rad)
        _omegas(rng, 2, np.pi - 1e-3, np.pi - 1e-4),  # near pi (log's quaternion has w ~ 1e-4)
    ]
    for w in cases:
        w_t = torch.tensor(w, requires_grad=True)
        assert torch.autograd.gradcheck(tt.so3_exp, (w_t,), eps=1e-7, atol=1e-7)
        xi = torch.tensor(np.concatenate([w, rng.normal(size=(2, 3))], 1), requires_grad=True)
        assert torch.autograd.gradcheck(tt.se3_exp, (xi,), eps=1e-7, atol=1e-7)
        # Logs are differentiated at valid rotations: compose with exp so the FD step stays on SO(3).
        assert torch.autograd.gradcheck(lambda x: tt.se3_log(tt.se3_exp(x)), (xi,), eps=1e-7, atol=1e-6)
    q = torch.tensor(rng.normal(size=(6, 4)), requires_grad=True)
    assert torch.autograd.gradcheck(tt.R_from_quat, (q,), eps=1e-7, atol=1e-7)
    assert torch.autograd.gradcheck(lambda x: tt.quat_from_R(tt.R_from_quat(x)), (q,), eps=1e-7, atol=1e-6)


def test_gradients_finite_and_exact_at_zero():
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    R = tt.so3_exp(w)
    # d exp(w)/dw at 0 is the generator: dR/dw_k = [e_k]_x, so d R[2,1] / d w_0 = 1.
    (g,) = torch.autograd.grad(R[2, 1], w)
    np.testing.assert_allclose(g.numpy(), [1.0, 0.0, 0.0], atol=1e-15)
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    out = tt.se3_log(tt.se3_exp(xi)).sum()
    (g,) = torch.autograd.grad(out, xi)
    np.testing.assert_allclose(g.numpy(), np.ones(6), atol=1e-12)
    T = torch.eye(4, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(tt.se3_log(T).square().sum(), T)
    assert torch.isfinite(g).all()
    R_pi = torch.tensor(tf.so3_exp([np.pi, 0, 0]), requires_grad=True)
    (g,) = torch.autograd.grad(tt.so3_log(R_pi).sum(), R_pi)
    assert torch.isfinite(g).all()


def test_shape_errors():
    with pytest.raises(ShapeError):
        tt.se3_exp(torch.zeros(5))
    with pytest.raises(ShapeError):
        tt.R_from_quat(torch.zeros(3, 3))

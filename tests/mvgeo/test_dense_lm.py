"""`mvgeo.dense_lm.dense_lm` against scipy's MINPACK Levenberg-Marquardt (`least_squares(method="lm")`)."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from mvgeo.dense_lm import dense_lm


def _exp_fit(rng):
    """y = a exp(-b x) + c sin(d x) + noise: 4 unknowns of very different scales, 200 residuals."""
    x = np.linspace(0, 10, 200)
    truth = np.array([3.0, 0.4, 0.05, 2.0])
    y = truth[0] * np.exp(-truth[1] * x) + truth[2] * np.sin(truth[3] * x) + rng.normal(scale=0.01, size=x.size)

    def fun(p):
        return p[0] * np.exp(-p[1] * x) + p[2] * np.sin(p[3] * x) - y

    def jac(p):
        e = np.exp(-p[1] * x)
        return np.stack([e, -p[0] * x * e, np.sin(p[3] * x), p[2] * x * np.cos(p[3] * x)], axis=1)

    return fun, jac, np.array([2.0, 0.3, 0.04, 2.02])


def _rosenbrock():
    """Rosenbrock's valley as residuals (10 (y - x^2), 1 - x): minimum 0 at (1, 1), a curved, badly scaled
    valley where plain Gauss-Newton steps overshoot and the damping has to work."""
    def fun(p):
        return np.array([10 * (p[1] - p[0] ** 2), 1 - p[0]])

    def jac(p):
        return np.array([[-20 * p[0], 10.0], [-1.0, 0.0]])

    return fun, jac, np.array([-1.2, 1.0])


@pytest.mark.parametrize("problem", ["exp_fit", "rosenbrock"])
def test_dense_lm_reaches_scipys_minimum(rng, problem):
    fun, jac, x0 = _exp_fit(rng) if problem == "exp_fit" else _rosenbrock()
    ref = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14,
                        max_nfev=10000)
    out = dense_lm(fun, jac, x0, max_nfev=1000, ftol=1e-14, xtol=1e-14, gtol=1e-14)
    assert out.converged
    # The same minimum: the cost to 1e-9 of its value (or 1e-20 absolute at Rosenbrock's zero), the
    # unknowns to 1e-6 of their size (the exp fit's are determined to about 1e-3 by its noise, so 1e-6
    # is a different-minimum test, not a noise test).
    assert out.cost <= ref.cost * (1 + 1e-9) + 1e-20
    np.testing.assert_allclose(out.x, ref.x, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(out.fun, fun(out.x))
    np.testing.assert_allclose(out.jac, jac(out.x))
    assert out.nfev <= 1000 and out.njev <= out.nfev


def test_dense_lm_stops_at_max_nfev_and_says_so():
    fun, jac, x0 = _rosenbrock()
    out = dense_lm(fun, jac, x0, max_nfev=8, ftol=0, xtol=0, gtol=0)
    assert not out.converged and out.nfev == 8
    assert 0 < out.cost < 0.5 * float(fun(x0) @ fun(x0))  # its accepted steps lowered the cost, not to 0


def test_dense_lm_at_a_minimum_stays_there():
    """A start at the exact minimum (zero gradient) returns it unchanged after one evaluation."""
    fun, jac, _ = _rosenbrock()
    out = dense_lm(fun, jac, np.array([1.0, 1.0]))
    assert out.converged and out.nfev == 1 and out.cost == 0.0
    np.testing.assert_array_equal(out.x, [1.0, 1.0])

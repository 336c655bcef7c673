"""Levenberg-Marquardt for small dense least-squares problems (numpy float64).

For problems with a handful of unknowns and many residuals, such as a two-view relative pose refined on
its inliers' Sampson distances (5 or 6 unknowns, tens to thousands of residuals), where scipy's
`least_squares` spends as much time in its own bookkeeping as in the residuals. Each iteration forms
the normal equations ``J^T J`` (n x n) and solves them with Marquardt's scaled damping
``(J^T J + mu D) h = -J^T r``, where ``D`` is the running maximum of ``diag(J^T J)`` (MINPACK's
scaling, which `least_squares(..., x_scale="jac")` also uses), so the result does not depend on the
units of the unknowns. The damping follows Nielsen's rule: after an accepted step with gain ratio
``rho``, ``mu *= max(1/3, 1 - (2 rho - 1)^3)``; after a rejected one ``mu *= nu``, ``nu *= 2``.

Stops, like `least_squares`, when an accepted step lowers the cost by at most ``ftol`` of it, when the
next step is predicted to lower it by at most that, when the step is at most ``xtol`` of ``|x|``, when
the gradient's largest entry is at most ``gtol``, or after ``max_nfev`` residual evaluations.
The tests compare the minimum it reaches with scipy's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DenseLMResult:
    """Attributes:
        x: (n,) the solution.
        fun: (m,) the residuals at `x`.
        jac: (m, n) the Jacobian at `x`.
        cost: ``0.5 |fun|^2``.
        nfev: residual evaluations.
        njev: Jacobian evaluations.
        converged: False when `max_nfev` ran out first.
    """

    x: np.ndarray
    fun: np.ndarray
    jac: np.ndarray
    cost: float
    nfev: int
    njev: int
    converged: bool


def dense_lm(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, *,
             max_nfev: int = 200, ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8,
             mu0: float = 1e-6) -> DenseLMResult:
    """Minimise ``0.5 |fun(x)|^2`` from `x0`.

    Args:
        fun: x (n,) -> residuals (m,).
        jac: x (n,) -> Jacobian (m, n) of `fun`.
        x0: (n,) start.
        max_nfev: at most this many evaluations of `fun`.
        ftol, xtol, gtol: the stopping tolerances (module docstring).
        mu0: the first damping, relative to ``D``.
    """
    x = np.array(x0, dtype=np.float64)
    r = np.asarray(fun(x), np.float64)
    J = np.asarray(jac(x), np.float64)
    nfev, njev = 1, 1
    cost = 0.5 * float(r @ r)
    A, g = J.T @ J, J.T @ r
    D = np.maximum(np.diag(A).copy(), np.finfo(float).tiny)
    mu, nu = mu0, 2.0
    converged = False
    while nfev < max_nfev:
        if not np.isfinite(cost) or np.abs(g).max() <= gtol:
            converged = np.isfinite(cost)
            break
        try:
            h = np.linalg.solve(A + mu * np.diag(D), -g)
        except np.linalg.LinAlgError:
            mu, nu = mu * nu, nu * 2.0
            continue
        predicted = 0.5 * float(h @ (mu * D * h - g))  # the model's reduction, > 0
        if np.linalg.norm(h) <= xtol * (np.linalg.norm(x) + xtol) or predicted <= ftol * cost:
            converged = True
            break
        x_new = x + h
        r_new = np.asarray(fun(x_new), np.float64)
        nfev += 1
        cost_new = 0.5 * float(r_new @ r_new)
        rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
        if rho > 0 and np.isfinite(cost_new):
            small = cost - cost_new <= ftol * cost
            x, r, cost = x_new, r_new, cost_new
            J = np.asarray(jac(x), np.float64)
            njev += 1
            A, g = J.T @ J, J.T @ r
            D = np.maximum(D, np.diag(A))
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small:
                converged = True
                break
        else:
            mu, nu = mu * nu, nu * 2.0
    return DenseLMResult(x, r, J, cost, nfev, njev, converged)

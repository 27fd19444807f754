"""Levenberg-Marquardt for a few dense parameters, with a forward-difference Jacobian.

What the small nonlinear fits (the gyroscope by integrating its turns) need of
``scipy.optimize.least_squares(method="lm", x_scale="jac")``, in numpy: importing
scipy.optimize costs ~0.2 s, a sixth of a whole ``imupipe run`` of imu_tk's pipeline
(``bench/peers_imu_tk.py``, section 4). The damping is scaled by the Jacobian's column
norms as MINPACK's is and the difference steps are scipy's ``2-point`` ones. The fit stops
when the Gauss-Newton step would gain less than ``TOL`` of the cost: the parameters are
then within ~1e-6 of their standard errors of the optimum (on imu_tk's data, 1.5e-10 of
the largest, as MINPACK's were).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

REL_STEP = np.finfo(float).eps ** 0.5  # scipy's 2-point step, relative to max(1, |x|)
TOL = 1e-14  # Gauss-Newton gain, relative to the cost, below which the fit stops


@dataclass
class LeastSquares:
    """The fit: ``x``, the residuals ``fun`` and Jacobian ``jac`` there, cost evaluations."""

    x: np.ndarray
    fun: np.ndarray
    jac: np.ndarray
    nfev: int
    success: bool


def jacobian(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(n, p) forward differences of ``fun`` at ``x`` (where it is ``r``)."""
    J = np.empty((len(r), len(x)))
    for j in range(len(x)):
        xh = x.copy()
        xh[j] += REL_STEP * (1.0 if x[j] >= 0 else -1.0) * max(1.0, abs(x[j]))
        J[:, j] = (fun(xh) - r) / (xh[j] - x[j])  # the step as represented
    return J


def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A^-1 b``, or its least-squares solution when ``A`` is singular (parameters the data
    leave free: the caller reports that, from the returned Jacobian's rank)."""
    return np.linalg.lstsq(A, b, rcond=None)[0]


def levenberg_marquardt(fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
                        max_nfev: int = 200) -> LeastSquares:
    """Minimise ``|fun(x)|^2`` from ``x0``; ``max_nfev`` cost evaluations, the Jacobian's included."""
    x = np.asarray(x0, float).copy()
    r = fun(x)
    J = jacobian(fun, x, r)
    nfev = 1 + len(x)
    cost = float(r @ r)
    lam = 1e-3
    while True:
        A, g = J.T @ J, J.T @ r
        if g @ _solve(A, g) <= TOL * cost:  # even the Gauss-Newton step would gain
            return LeastSquares(x, r, J, nfev, True)  # nothing: rounding decides
        if nfev + 1 + len(x) > max_nfev:
            break
        d = -_solve(A + lam * np.diag(np.diag(A)), g)
        r2 = fun(x + d)
        nfev += 1
        cost2 = float(r2 @ r2)
        if np.isfinite(cost2) and cost2 <= cost:
            x, r, cost = x + d, r2, cost2
            J = jacobian(fun, x, r)
            nfev += len(x)
            lam = max(lam / 10.0, 1e-12)
        else:
            lam *= 10.0
    return LeastSquares(x, r, J, nfev, False)

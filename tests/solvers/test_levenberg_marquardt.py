"""imupipe.solvers.levenberg_marquardt against scipy's MINPACK fit, and where the data leave
parameters free."""

from __future__ import annotations

import numpy as np
import pytest
from method_b_synth import make_session
from scipy.optimize import least_squares

from imupipe.errors import SolverError
from imupipe.observations import GyroObservations, Turns
from imupipe.solvers.gyro_integration import GyroIntegration, GyroIntegrationParams
from imupipe.solvers.levenberg_marquardt import levenberg_marquardt


def _decays(seed: int):
    """Two decaying exponentials in noise: a nonlinear fit of four constants."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 10, 200)
    truth = np.array([2.0, 0.3, -1.0, 1.5])

    def model(x):
        return x[0] * np.exp(-x[1] * t) + x[2] * np.exp(-x[3] * t)

    y = model(truth) + 0.01 * rng.normal(size=len(t))
    return (lambda x: model(x) - y), np.array([1.0, 0.1, -0.5, 1.0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lands_on_minpacks_optimum(seed):
    fun, x0 = _decays(seed)
    fit = levenberg_marquardt(fun, x0)
    tight = least_squares(fun, x0, method="lm", x_scale="jac", ftol=1e-15, xtol=1e-15, gtol=1e-15)
    assert fit.success and fit.nfev <= 200
    assert np.abs(fit.x - tight.x).max() < 1e-7 * np.abs(tight.x).max()
    np.testing.assert_array_equal(fit.fun, fun(fit.x))
    np.testing.assert_allclose(fit.jac, tight.jac, rtol=1e-5, atol=1e-6)  # both by differences


def test_stops_at_max_nfev_unconverged():
    fun, x0 = _decays(0)
    fit = levenberg_marquardt(fun, x0, max_nfev=12)
    assert not fit.success and fit.nfev <= 12


def test_free_parameters_do_not_break_the_fit():
    """Only x0 + x1 is determined: the fit still ends, and its Jacobian shows the rank."""
    fit = levenberg_marquardt(lambda x: np.array([x[0] + x[1] - 1.0, 2 * (x[0] + x[1]) - 2.0]),
                              np.array([3.0, 0.5]))
    assert fit.success and abs(fit.x.sum() - 1.0) < 1e-9
    assert np.linalg.matrix_rank(fit.jac) == 1


def test_gyro_integration_says_the_turns_leave_constants_free():
    """Turns about z alone (no bias) leave the constants of x and y free: a SolverError."""
    s = make_session(5)
    turns = Turns(s.turns.before, s.turns.after, s.turns.t,
                  tuple(g * [0.0, 0.0, 1.0] for g in s.turns.gyro))
    r = s.rests
    obs = GyroObservations(s.gravity_body, 0 * r.mean["gyro"], r.cov_of_mean("gyro"), turns)
    with pytest.raises(SolverError, match="do not determine all nine"):
        GyroIntegration().solve(obs, GyroIntegrationParams(scale_search=False))

"""Method A thermal fit: identification Kalman filter and the polynomial alternative."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.errors import SolverError
from imupipe.observations import ThermalObservations
from imupipe.solvers.thermal_kalman import ThermalKalman, ThermalKalmanParams
from imupipe.solvers.thermal_poly import ThermalPoly, ThermalPolyParams

K_TOL_SIGMA = 5.0


def warmup(seed: int, span_C: float = 20.0, n: int = 3600, cubic: float = 0.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    T = 22 + span_C * (1 - np.exp(-t / 600))
    b0, k = np.array([0.01, -0.02, 0.005]), np.array([2e-4, -1e-4, 5e-5])
    sigma = np.array([1e-4, 1e-4, 2e-4])
    y = b0 + np.outer(T - 25, k) + cubic * np.outer((T - 25) ** 3, [1, 1, 1])
    y = y + rng.normal(size=(n, 3)) * sigma
    return ThermalObservations("gyro", t, T, y, sigma), b0, k


def test_kalman_recovers_b0_and_k_with_its_covariance():
    obs, b0, k = warmup(0)
    fit = ThermalKalman().solve(obs, ThermalKalmanParams())
    sd = np.sqrt(np.diag(fit.cov))
    assert np.all(np.abs(fit.k - k) < K_TOL_SIGMA * sd[3:])
    assert np.all(np.abs(fit.b0 - b0) < K_TOL_SIGMA * sd[:3])
    assert np.all(sd[3:] < 1e-5)


def test_poly_recovers_cubic_law_slope():
    obs, _, k = warmup(1, cubic=1e-7)
    fit = ThermalPoly().solve(obs, ThermalPolyParams(degree=3))
    assert np.all(np.abs(fit.k - k) < 5 * np.sqrt(np.diag(fit.cov))[3:])
    assert np.allclose(np.array(fit.details["coefficients"])[:, 3], 1e-7, rtol=0.05)


def test_refuses_a_warmup_without_temperature_change():
    obs, _, _ = warmup(2, span_C=0.5)
    with pytest.raises(SolverError, match="degC"):
        ThermalKalman().solve(obs, ThermalKalmanParams())

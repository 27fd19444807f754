"""The thermal Kalman filter gives batch least squares in any units (raw counts included)."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.observations import ThermalObservations
from imupipe.solvers.thermal_kalman import ThermalKalman, ThermalKalmanParams
from imupipe.solvers.thermal_poly import ThermalPoly, ThermalPolyParams

K_TOL_SIGMA = 5.0
LS_REL_TOL = 1e-8  # "up to rounding": relative to the estimate's own standard deviation


def counts_warmup(seed: int = 3, n: int = 3600):
    """A 16-bit gyro in counts: bias 36828 counts, k of a few counts per degC."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    T = 22 + 20 * (1 - np.exp(-t / 600))
    b0, k = np.array([36828.0, -1200.0, 500.0]), np.array([2.0, -1.0, 0.5])
    sigma = np.array([3.0, 3.0, 4.0])
    y = b0 + np.outer(T - 25, k) + rng.normal(size=(n, 3)) * sigma
    return ThermalObservations("gyro", t, T, y, sigma), b0, k


@pytest.mark.parametrize("p0", [None, 1.0])
def test_kalman_equals_least_squares_for_a_large_offset(p0):
    obs, b0, k = counts_warmup()
    fit = ThermalKalman().solve(obs, ThermalKalmanParams(p0=p0))
    ls = ThermalPoly().solve(obs, ThermalPolyParams(degree=1))
    sd = np.sqrt(np.diag(fit.cov))
    assert np.all(np.abs(fit.k - ls.k) < LS_REL_TOL * sd[3:] + (0 if p0 is None else 1e-3 * sd[3:]))
    assert np.all(np.abs(fit.b0 - ls.b0) < LS_REL_TOL * sd[:3] + (0 if p0 is None else 1e-3 * sd[:3]))
    assert np.allclose(fit.cov, ls.cov, rtol=1e-6 if p0 is None else 1e-3)  # the filter's P
    assert np.all(np.abs(fit.k - k) < K_TOL_SIGMA * sd[3:])
    assert np.all(np.abs(fit.b0 - b0) < K_TOL_SIGMA * sd[:3])


def test_kalman_is_unit_invariant():
    obs, _, _ = counts_warmup()
    fit = ThermalKalman().solve(obs, ThermalKalmanParams(p0=1.0))
    scaled = ThermalObservations(obs.sensor, obs.t_s, obs.T, obs.y * 1e-4, obs.sigma * 1e-4)
    fit_s = ThermalKalman().solve(scaled, ThermalKalmanParams(p0=1.0))
    assert np.allclose(fit_s.k * 1e4, fit.k, rtol=1e-9)
    assert np.allclose(fit_s.b0 * 1e4, fit.b0, rtol=1e-12)

"""``Calibration.apply``/``predict`` with the model terms ``imupipe diagnose`` accepted."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.errors import ConfigError
from imupipe.models import Calibration, TriadCalibration

R_M = np.array([0.03, -0.02, 0.01])
ACCEL = TriadCalibration("accel", np.array([[1.02, 0.01, 0], [0, 0.98, 0.02], [0, 0, 1.01]]), np.array([0.1, -0.2, 0.05]))
GYRO = TriadCalibration("gyro", np.eye(3) * 1.01, np.array([1e-3, 0, -2e-3]), np.array([2e-4, -1e-4, 5e-5]))


def _calibration(terms: list[dict]) -> Calibration:
    cal = Calibration({"accel": ACCEL, "gyro": GYRO}, {"model_terms": terms})
    return Calibration.from_json(cal.to_json())  # the terms travel through calibration.json


def test_a_lever_arm_term_is_predicted_and_removed_exactly():
    rng = np.random.default_rng(0)
    x, w, a = rng.normal(0, 9.8, (50, 3)), rng.normal(0, 3, (50, 3)), rng.normal(0, 10, (50, 3))
    cal = _calibration([{"effect": "lever_arm", "sensor": "accel", "parameters": {"r_m": R_M.tolist()}}])
    signals = {"omega": w, "alpha": a}
    y = cal.predict("accel", x, signals=signals)
    expected = ACCEL.predict(x + np.cross(a, R_M) + np.cross(w, np.cross(w, R_M)))
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cal.apply("accel", y, signals=signals), x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cal.apply("gyro", y), GYRO.apply(y))  # terms of other triads only


def test_gyro_g_sensitivity_and_quadratic_temperature_bias_terms_and_a_missing_signal():
    rng = np.random.default_rng(1)
    w, f, T = rng.normal(0, 1, (20, 3)), rng.normal(0, 9.8, (20, 3)), rng.uniform(10, 40, 20)
    G = np.arange(9.0).reshape(3, 3) * 1e-5
    k2 = np.array([1e-6, -2e-6, 3e-6])
    cal = _calibration([
        {"effect": "gyro_g_sensitivity", "sensor": "gyro", "parameters": {"G": G.tolist()}},
        {"effect": "bias_temperature_nonlinear", "sensor": "gyro", "parameters": {"k2_per_C2": k2.tolist(), "sensor": "gyro"}},
    ])
    y = cal.predict("gyro", w, T, signals={"f": f})
    np.testing.assert_allclose(y, GYRO.predict(w, T) + f @ G.T + np.outer((T - 25) ** 2, k2), atol=1e-15)
    np.testing.assert_allclose(cal.apply("gyro", y, T, signals={"f": f}), w, atol=1e-12)
    with pytest.raises(ConfigError, match="'f'"):
        cal.apply("gyro", y, T)


def test_gyro_scale_and_thermal_lag_terms():
    rng = np.random.default_rng(2)
    w, T, rate = rng.normal(0, 1, (20, 3)), rng.uniform(10, 40, 20), rng.normal(0, 0.02, 20)
    ppm, eps, tau = np.array([100.0, -50.0, 30.0]), np.array([1e-3, -2e-3, 5e-4]), 60.0
    cal = _calibration([
        {"effect": "gyro_scale_temperature", "sensor": "gyro", "parameters": {"ppm_per_C": ppm.tolist()}},
        {"effect": "gyro_scale_asymmetry", "sensor": "gyro", "parameters": {"eps": eps.tolist()}},
        {"effect": "thermal_lag", "sensor": "temperature", "parameters": {"tau_s": tau}},
    ])
    y = cal.predict("gyro", w, T, signals={"T_rate": rate})
    sensed = w @ GYRO.S.T
    lag = tau * np.outer(rate, GYRO.k)  # the bias follows the die, tau dT/dt ahead of the read-out
    expected = GYRO.predict(w, T) + sensed * np.outer(T - 25, ppm * 1e-6) + np.abs(sensed) * eps + lag
    np.testing.assert_allclose(y, expected, atol=1e-15)
    # the terms are evaluated at the nominal correction: exact to first order (terms ~1e-3 of x)
    np.testing.assert_allclose(cal.apply("gyro", y, T, signals={"T_rate": rate}), w, atol=1e-5)
    with pytest.raises(ConfigError, match="'T_rate'"):
        cal.predict("gyro", w, T)
    # the read-out's lag is the temperature's: it moves every triad's bias along its own k
    accel = TriadCalibration("accel", ACCEL.M, ACCEL.b0, np.array([1e-3, -2e-3, 5e-4]))
    lagged = Calibration({"accel": accel}, {"model_terms": [
        {"effect": "thermal_lag", "sensor": "temperature", "parameters": {"tau_s": tau}}]})
    f = rng.normal(0, 9.8, (20, 3))
    np.testing.assert_allclose(lagged.predict("accel", f, T, signals={"T_rate": rate}),
                               accel.predict(f, T) + tau * np.outer(rate, accel.k), atol=1e-12)

"""Method A gyroscope (Rodrigues, eqs. 27-37): exact finite rotations vs the small-angle sum."""

from __future__ import annotations

import numpy as np
import pytest
from method_a_synth import S_GYR, gyro_session

from imupipe.errors import SolverError
from imupipe.solvers.gyro_rodrigues import GyroRodrigues, GyroRodriguesParams, angle_error

EXACT_TOL_PPM = 5.0  # noise-free: exact up to the fixed-point iteration
NOISY_TOL_PPM = 5000.0  # 120 turns of <= 5 deg with 0.5 mrad/s noise


def error_ppm(M: np.ndarray) -> float:
    return float(np.abs(M @ S_GYR - np.eye(3)).max() * 1e6)


@pytest.mark.parametrize("max_deg", [5.0, 30.0])
def test_exact_rotation_recovers_noise_free_truth(max_deg):
    obs, _ = gyro_session(40, max_deg, np.random.default_rng(0))
    fit = GyroRodrigues().solve(obs, GyroRodriguesParams(exact_rotation=True))
    assert error_ppm(fit.M) < EXACT_TOL_PPM


def test_exact_rotation_survives_coning():
    obs, _ = gyro_session(40, 5.0, np.random.default_rng(1), coning=0.2)
    exact = GyroRodrigues().solve(obs, GyroRodriguesParams(exact_rotation=True))
    small = GyroRodrigues().solve(obs, GyroRodriguesParams(exact_rotation=False))
    assert error_ppm(exact.M) < 50.0
    assert error_ppm(small.M) > 10 * error_ppm(exact.M)


def test_small_angle_is_biased_by_large_turns():
    obs, _ = gyro_session(40, 30.0, np.random.default_rng(2))
    small = GyroRodrigues().solve(obs, GyroRodriguesParams(exact_rotation=False))
    assert error_ppm(small.M) > 1000.0  # tan(chi/2) ~ chi/2 fails at 30 deg: the reason for the option


def test_noisy_recovery_within_reported_uncertainty():
    # gyro noise 0.5 mrad/s per 100 Hz sample: the method is noise-limited (one scalar
    # equation per turn), so the check is against the covariance the solver reports
    obs, _ = gyro_session(120, 5.0, np.random.default_rng(3), noise=0.0005)
    fit = GyroRodrigues().solve(obs, GyroRodriguesParams())
    err = (fit.M @ S_GYR - np.eye(3)) @ np.linalg.inv(S_GYR)  # error of M itself
    sd = np.sqrt(np.diag(fit.cov)[:9]).reshape(3, 3)
    assert np.abs(err).max() * 1e6 < NOISY_TOL_PPM
    assert np.all(np.abs(err) < 5 * sd + 50e-6)


def test_turn_angle_error_is_zero_for_true_rotation():
    g0 = np.array([[0.0, 1.0, 0.0]])
    chi = np.radians(4.0)
    Y = np.array([[np.tan(chi / 2), 0.0, 0.0]])  # body turns about x by chi
    g1 = np.array([[0.0, np.cos(chi), -np.sin(chi)]])  # gravity seen in the body after it
    assert abs(angle_error(g0, g1, Y)[0]) < 1e-12
    Y_bad = Y * np.tan(chi * 1.01 / 2) / np.tan(chi / 2)
    assert abs(np.degrees(angle_error(g0, g1, Y_bad)[0]) - 0.04) < 1e-3


def test_refuses_too_few_turns():
    obs, _ = gyro_session(6, 5.0, np.random.default_rng(4))
    with pytest.raises(SolverError, match="turns"):
        GyroRodrigues().solve(obs, GyroRodriguesParams())

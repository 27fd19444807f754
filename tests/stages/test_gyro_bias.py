"""The gyro stage writes the bias its solver returns: a solver's bias option reaches the table."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.components import BoundSolver
from imupipe.models import TriadCalibration, triads_from_table, triads_to_table
from imupipe.observations import Rests, Turns
from imupipe.sim.api import simulate_recording
from imupipe.solvers.gyro_integration import GyroIntegration, GyroIntegrationParams, rest_bias
from imupipe.solvers.gyro_rodrigues import GyroRodrigues, GyroRodriguesParams
from imupipe.stages import gyro, segment

K_GYRO = np.array([2e-5, -3e-5, 1e-5])  # rad/s per degC, a made-up thermal stage's answer


@pytest.fixture(scope="module")
def inputs():
    rec, truth = simulate_recording("standard", None, 3, n_positions=40, warmup_s=60)
    d = dict(rec.device("imu"))
    seg = segment.STAGE.func(d, segment.SegmentParams(), None)
    return {"rests": seg["rests"], "turns": seg["turns"], "gyro": d["gyro"],
            "accel": triads_to_table([truth.calibration["accel"]])}


def stage_b0(inputs, solver, params, thermal: bool = False) -> np.ndarray:
    if thermal:
        inputs = {**inputs, "thermal": triads_to_table([TriadCalibration("gyro", np.eye(3), k=K_GYRO)])}
    out = gyro.STAGE.func(inputs, gyro.GyroParams(), BoundSolver(solver, params))
    (cal,) = triads_from_table(out["calibration"])
    return cal.b0


def test_bias_option_of_gyro_integration_is_the_calibrations_bias(inputs):
    rests = Rests.from_table(inputs["rests"])
    means = rests.need("gyro")
    first = stage_b0(inputs, GyroIntegration(), GyroIntegrationParams(bias="first_rest"))
    every = stage_b0(inputs, GyroIntegration(), GyroIntegrationParams(bias="all_rests"))
    np.testing.assert_allclose(first, means[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(every, rest_bias(means, rests.cov_of_mean("gyro"))[0], rtol=0, atol=1e-15)
    assert np.abs(first - every).max() > 1e-6  # the rests differ: the option shows


def test_thermal_stage_refers_the_solvers_bias_to_25_degc(inputs):
    rests = Rests.from_table(inputs["rests"])
    first = stage_b0(inputs, GyroIntegration(), GyroIntegrationParams(bias="first_rest"), thermal=True)
    expected = rests.need("gyro")[0] - K_GYRO * np.nan_to_num(rests.temperature[0] - 25.0)
    np.testing.assert_allclose(first, expected, rtol=0, atol=1e-15)


def test_gyro_rodrigues_bias_is_the_rests_around_its_turns(inputs):
    # the paper: a turn's bias is the mean of the rests before and after it; the fit uses the
    # turns that tilt gravity (this session's others, on the turntable, tilt it by < 0.02 deg)
    b0 = stage_b0(inputs, GyroRodrigues(), GyroRodriguesParams())
    rests = Rests.from_table(inputs["rests"])
    means, up = rests.need("gyro"), rests.need("accel")
    up = up / np.linalg.norm(up, axis=1, keepdims=True)
    turns = Turns.from_tables(inputs["turns"], inputs["gyro"])
    tilt = np.degrees(np.arccos(np.clip(np.sum(up[turns.before] * up[turns.after], axis=1), -1, 1)))
    used = tilt >= GyroRodriguesParams().min_tilt_deg
    assert 0 < used.sum() < len(turns)
    expected = 0.5 * (means[turns.before] + means[turns.after])[used].mean(axis=0)
    np.testing.assert_allclose(b0, expected, rtol=0, atol=1e-15)

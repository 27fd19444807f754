"""refine_joint with a gyro bias random walk: the drift model keeps the turns' chi2/dof at 1.

A simulated gimbal session (45 deg grid + 30 rotations, 3 s rests) whose gyro bias walks
(``GYRO_RW``, white noise otherwise), refined twice: with the default drift model (the
walk's intensity estimated from the rests) and with a constant bias (``gyro_bias_rw = 0``).
Tolerances as in test_refine_residuals: 3.5 sd of a chi2 over its dof.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from stage_chain import method_b_refine_inputs, run_stage, white_imu

from imupipe.models import Calibration
from imupipe.plugins import make_registry
from imupipe.sim.api import simulate_recording

N_SD = 3.5
GYRO_RW = 1e-5  # rad/s/sqrt(s): a strong walk so that a short session shows it
RW_FACTOR = 2.0  # the estimated intensity's sigma within this factor of the simulated one
CHI2_GROWTH = 1.5  # turn chi2/dof of the constant-bias model: far above the null band


@pytest.fixture(scope="module")
def drift_runs() -> dict[str, dict]:
    seed = 7
    rec, _ = simulate_recording("gimbal", None, seed, imu=white_imu(seed, gyro_bias_rw=GYRO_RW),
                                grid_deg=45.0, n_rotations=30, rest_s=3.0)
    reg = make_registry()
    inputs = method_b_refine_inputs(reg, rec)
    return {"walk": run_stage(reg, "refine_joint", inputs),
            "constant": run_stage(reg, "refine_joint", inputs, solver_params={"gyro_bias_rw": 0.0})}


def _blocks(out: dict) -> dict:
    return json.loads(out["residuals"].schema.metadata[b"imupipe.summary"])["blocks"]


def _turn_table_chi2(out: dict) -> tuple[float, int]:
    t = out["turn_residuals"]
    used = np.array(t["used"].to_pylist())
    return float(np.sum(t["chi2"].to_numpy()[used])), 2 * int(used.sum())


def test_walk_intensity_is_estimated_from_the_rests(drift_runs):
    walk = Calibration.from_tables(drift_runs["walk"]["calibration"])["gyro"].details["joint"]["gyro_bias_walk"]
    assert walk["estimated"]
    sigma = np.array(walk["sigma_rw"])
    assert np.all((sigma > GYRO_RW / RW_FACTOR) & (sigma < GYRO_RW * RW_FACTOR)), sigma
    const = Calibration.from_tables(drift_runs["constant"]["calibration"])["gyro"].details["joint"]
    assert const["gyro_bias_walk"]["q"] == [0.0, 0.0, 0.0] and not const["gyro_bias_walk"]["estimated"]


def test_drift_model_keeps_turn_and_gyro_rest_chi2_at_one(drift_runs):
    blocks = _blocks(drift_runs["walk"])
    for name in ("turn", "gyro_rest", "accel_rest"):
        b = blocks[name]
        assert abs(b["chi2_per_dof"] - 1) < N_SD * np.sqrt(2 / b["dof"]), (name, b)
    chi2, rows = _turn_table_chi2(drift_runs["walk"])  # the table's own noise model has the walk too
    assert abs(chi2 / rows - 1) < N_SD * np.sqrt(2 / rows) + 12 / rows, chi2 / rows


def test_constant_bias_model_shows_the_drift(drift_runs):
    blocks = _blocks(drift_runs["constant"])
    for name in ("turn", "gyro_rest"):
        assert blocks[name]["chi2_per_dof"] > CHI2_GROWTH, (name, blocks[name])
    chi2, rows = _turn_table_chi2(drift_runs["constant"])
    assert chi2 / rows > CHI2_GROWTH

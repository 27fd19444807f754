"""refine_joint's residual outputs: schemas, chi2/dof = 1 on white noise, growth under omitted physics.

Simulated gimbal sessions (45 deg grid + 30 rotations, 70 rests, 69 turns) with white noise
only, run through segmentation, method B's accel and gyro stages and the refinement.
Tolerances: a chi2 over ``dof`` independent unit normals has sd ``sqrt(2 / dof)``; the
checks allow 3.5 sd (a seeded null fails them with probability < 1e-3).
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow.compute as pc
import pytest
from method_b_synth import G, make_session, session_tables
from stage_chain import method_b_refine_inputs, run_stage, white_imu

from imupipe import schemas
from imupipe.models import Calibration, TriadCalibration, triads_to_table
from imupipe.observations import Rests, Turns
from imupipe.plugins import make_registry
from imupipe.sim.api import simulate_recording
from imupipe.solvers.joint_ml import JointMLParams, JointObservations, joint_model

N_SD = 3.5
GYRO_PARAMS = 12  # M_g (9), b_g (3): what the fit can absorb of the turn mismatches
G_SENS = [[2e-5, 0.0, 0.0], [0.0, -1.5e-5, 0.0], [0.0, 0.0, 1e-5]]  # rad/s per m/s^2 (~0.01 deg/s/g)
CHI2_GROWTH = 3.0  # chi2/dof with the omitted effect: far above the null band (< 1.4 here)


def _refined(effects: dict | None, seed: int = 5) -> dict:
    rec, _ = simulate_recording("gimbal", effects, seed, imu=white_imu(seed), grid_deg=45.0,
                                n_rotations=30, rest_s=3.0)
    reg = make_registry()
    return run_stage(reg, "refine_joint", method_b_refine_inputs(reg, rec))


@pytest.fixture(scope="module")
def null_run() -> dict:
    return _refined(None)


@pytest.fixture(scope="module")
def g_sensitive_run() -> dict:
    return _refined({"gyro_g_sensitivity": {"G": G_SENS}})


def _rest_chi2(out: dict, sensor: str) -> tuple[float, int]:
    t = out["residuals"].filter(pc.equal(out["residuals"]["sensor"], sensor))
    z = np.array(t["normalised"].to_pylist())
    return float(np.sum(z**2)), z.size


def _turn_chi2(out: dict) -> tuple[float, int]:
    t = out["turn_residuals"]
    used = np.array(t["used"].to_pylist())
    return float(np.sum(np.array(t["chi2"].to_pylist())[used])), 2 * int(used.sum())


def test_residual_tables_follow_their_schemas(null_run):
    res, turns = null_run["residuals"], null_run["turn_residuals"]
    schemas.check(res, "residuals")
    schemas.check(turns, "turn_residuals")
    assert set(res["stage"].to_pylist()) == {"refine_joint"}
    assert sorted(set(res["sensor"].to_pylist())) == ["accel", "gyro"]
    assert set(res["kind"].to_pylist()) == {"rest"}
    n_rests = res.num_rows // 2
    assert turns.num_rows == n_rests - 1 and all(turns["used"].to_pylist())
    w = np.array(turns["whitened"].to_pylist())
    np.testing.assert_allclose(np.sum(w**2, axis=1), turns["chi2"].to_numpy(), rtol=1e-12)
    assert 10.0 < np.median(turns["angle_deg"].to_numpy()) < 130.0
    summary = json.loads(turns.schema.metadata[b"imupipe.summary"])
    assert {"accel_rest", "gyro_rest", "turn"} <= set(summary["blocks"])


def test_calibration_details_record_noise_model_and_chi2(null_run):
    cal = Calibration.from_tables(null_run["calibration"])
    for sensor, sd in (("accel", 0.5e-3 * 9.80665), ("gyro", np.radians(0.02))):
        d = cal[sensor].details
        white = np.array(d["noise"]["white_sigma"])
        assert np.all(np.abs(white / sd - 1) < 0.2), white  # the simulated white noise, per axis
        assert d["joint"]["blocks"]["turn"]["dof"] > 0 and np.isfinite(d["joint"]["chi2_per_dof"])
    assert "rest_to_rest_bias_sigma" in cal["gyro"].details["noise"]


def test_white_noise_gives_unit_chi2_per_dof(null_run):
    blocks = json.loads(null_run["residuals"].schema.metadata[b"imupipe.summary"])["blocks"]
    for name in ("accel_rest", "gyro_rest", "turn"):  # the joint likelihood's own blocks
        b = blocks[name]
        assert abs(b["chi2_per_dof"] - 1) < N_SD * np.sqrt(2 / b["dof"]), (name, b)
    # The tables: gyro rests absorb b_g (3); accel rests the nuisance directions (block dof).
    chi2, rows = _rest_chi2(null_run, "gyro")
    assert abs(chi2 / (rows - 3) - 1) < N_SD * np.sqrt(2 / rows)
    chi2, _ = _rest_chi2(null_run, "accel")
    dof = blocks["accel_rest"]["dof"]
    assert abs(chi2 / dof - 1) < N_SD * np.sqrt(2 / dof)
    chi2, rows = _turn_chi2(null_run)  # measured directions: the fit absorbs at most 12 of them
    assert 1 - GYRO_PARAMS / rows - N_SD * np.sqrt(2 / rows) < chi2 / rows < 1 + N_SD * np.sqrt(2 / rows)


def test_omitted_g_sensitivity_shows_in_turns_and_gyro_rests(null_run, g_sensitive_run):
    chi2, rows = _turn_chi2(g_sensitive_run)
    null_chi2, _ = _turn_chi2(null_run)
    assert chi2 / rows > CHI2_GROWTH and chi2 > 3 * null_chi2
    chi2, rows = _rest_chi2(g_sensitive_run, "gyro")
    assert chi2 / (rows - 3) > CHI2_GROWTH
    blocks = json.loads(g_sensitive_run["turn_residuals"].schema.metadata[b"imupipe.summary"])["blocks"]
    assert blocks["turn"]["chi2_per_dof"] > CHI2_GROWTH


def test_turn_rows_at_the_truth_are_chi2_with_two_dof_per_turn():
    """Observation level, true calibration and true gravity directions: nothing fitted, so the
    turn rows' chi2 / rows = 1 within its sd."""
    s = make_session(41, n_rests=60)
    tables = session_tables(s)
    truth = [TriadCalibration("accel", np.linalg.inv(s.S_accel), s.b_accel),
             TriadCalibration("gyro", np.linalg.inv(s.S_gyro), s.b_gyro)]
    reg = make_registry()
    out = run_stage(reg, "refine_joint", {**tables, "accel_calibration": triads_to_table(truth[:1]),
                                     "gyro_calibration": triads_to_table(truth[1:])}, g_m_s2=G)
    rests = Rests.from_table(tables["rests"])
    turns = Turns.from_tables(tables["turns"], tables["gyro"], rests.t0_ns)
    model, _, _ = joint_model(JointObservations(rests, turns, G, *truth),
                              JointMLParams(gyro_bias_rw=0.0, accel_bias_rw=0.0))
    x_l = np.zeros(model.stages.size)
    x_l[model.stages.delta] = np.einsum("nia,ni->na", model.B, s.gravity_body)  # the true directions
    r = model.residuals(model.x_g0, x_l)[0][model.rows.of("turn")]
    assert abs(r @ r / len(r) - 1) < N_SD * np.sqrt(2 / len(r))  # no parameter fitted here
    assert 2 * out["turn_residuals"].num_rows == len(r)

"""Stage refine_joint: registered, wired by tables, refines a start from either method."""

from __future__ import annotations

import numpy as np
from method_b_synth import G, make_session, session_tables

from imupipe import schemas
from imupipe.components import BoundSolver
from imupipe.models import Calibration, TriadCalibration, triads_to_table
from imupipe.plugins import make_registry
from imupipe.solvers.joint_ml import JointMLParams
from imupipe.stages.refine import RefineParams

ACC_SHAPE_TOL_PPM = 200.0
GYRO_SHAPE_TOL_PPM = 600.0


def _start_tables(s):
    rng = np.random.default_rng(1)
    accel = TriadCalibration("accel", np.linalg.inv(s.S_accel + np.tril(1e-3 * rng.normal(size=(3, 3)))),
                             s.b_accel + 0.02, solver="ellipsoid_svd")
    gyro = TriadCalibration("gyro", np.linalg.inv(s.S_gyro) @ (np.eye(3) + 1e-3 * rng.normal(size=(3, 3))),
                            s.b_gyro, solver="gyro_integration")
    return triads_to_table([accel]), triads_to_table([gyro])


def test_refine_joint_is_registered_with_its_solver():
    reg = make_registry()
    stage = reg.get("stages", "refine_joint")
    assert stage.solver_kind == "joint"
    assert reg.get("solvers", "joint_ml").kind == "joint"
    assert reg.get("solvers", "ellipsoid_svd").kind == "accel"
    assert reg.get("solvers", "gyro_integration").kind == "gyro"
    assert {"split_control", "validate_control"} <= set(reg.names("stages"))


def test_refine_joint_stage_returns_refined_calibration_with_sigmas():
    s = make_session(21, n_rests=40)
    tables = session_tables(s)
    accel_t, gyro_t = _start_tables(s)
    stage = make_registry().get("stages", "refine_joint")
    solver = BoundSolver(make_registry().get("solvers", "joint_ml"), JointMLParams())
    out = stage.func({**tables, "accel_calibration": accel_t, "gyro_calibration": gyro_t},
                     RefineParams(g_m_s2=G), solver)
    schemas.check(out["calibration"], "calibration")
    cal = Calibration.from_tables(out["calibration"])
    assert np.abs(cal["accel"].M @ s.S_accel - np.eye(3)).max() * 1e6 < ACC_SHAPE_TOL_PPM
    assert np.abs(cal["gyro"].M @ s.S_gyro - np.eye(3)).max() * 1e6 < GYRO_SHAPE_TOL_PPM
    for sensor in ("accel", "gyro"):
        d = cal[sensor].details
        assert np.shape(d["sigma_M"]) == (3, 3) and np.all(np.isfinite(d["sigma_b0"]))
        assert d["start_solver"] in ("ellipsoid_svd", "gyro_integration")
    assert np.shape(cal["accel"].details["joint_covariance"]) == (30, 30)

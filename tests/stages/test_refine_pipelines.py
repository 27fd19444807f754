"""pipelines/gimbal-optimization.toml and pipelines/imu_tk.toml through the runner."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import polar

from imupipe.models import Calibration
from imupipe.pipeline.api import run_sessions
from imupipe.sim.api import simulate_recording, write_csv

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "sessions"
MG = 9.80665e-3
ACC_SHAPE_TOL_PPM = 200.0  # after removing the common scale: the pipeline's g is 9.80665, the
ACC_SCALE_TOL_PPM = 2000.0  # simulated local g (Moscow) is ~900 ppm larger
ACC_BIAS_TOL_MG = 0.2
GYRO_SHAPE_TOL_PPM = 300.0
GYRO_ALIGN_TOL_DEG = 0.02


@pytest.fixture(scope="module")
def gimbal_csv(tmp_path_factory) -> tuple[Path, object]:
    """A short gimbal session (45 deg grid, 30 rotations) with the default sensor and warm-up."""
    rec, truth = simulate_recording("gimbal", {}, 4, grid_deg=45.0, n_rotations=30, rest_s=3.0)
    path = tmp_path_factory.mktemp("sim") / "gimbal.csv"
    write_csv(path, rec)
    return path, truth


def test_gimbal_pipeline_recovers_with_refinement_and_control(gimbal_csv, tmp_path):
    path, truth = gimbal_csv
    written = run_sessions([path], PIPELINES / "gimbal-optimization.toml", tmp_path, quiet=True)
    cal = Calibration.from_json(written[0].read_text())
    true = truth.calibration
    assert cal["accel"].solver == cal["gyro"].solver == "joint_ml"
    Qa, Ha = polar(cal["accel"].M @ true["accel"].S)
    Qg, Hg = polar(cal["gyro"].M @ true["gyro"].S)
    scale = np.trace(Ha) / 3
    assert np.abs(Ha / scale - np.eye(3)).max() * 1e6 < ACC_SHAPE_TOL_PPM
    assert abs(scale - 1) * 1e6 < ACC_SCALE_TOL_PPM
    assert np.abs(cal["accel"].b0 - true["accel"].b0).max() / MG < ACC_BIAS_TOL_MG
    assert np.abs(Hg - np.eye(3)).max() * 1e6 < GYRO_SHAPE_TOL_PPM
    align = np.degrees(np.arccos(np.clip((np.trace(Qg @ Qa.T) - 1) / 2, -1, 1)))
    assert align < GYRO_ALIGN_TOL_DEG
    joint = cal["accel"].details["joint"]
    assert joint["fitted_temperature_coefficients"] and 0.7 < joint["chi2_per_dof"] < 1.5
    run = json.loads((written[0].parent / "run.json").read_text())
    assert run["stages"]["control"]["status"] == "ran"
    report = (written[0].parent / "report.md").read_text()
    assert "## Whitened residuals of the joint fit (refine_joint)" in report
    assert f"chi2/dof {joint['chi2_per_dof']:.3g}" in report
    assert (written[0].parent / "figures" / "refine_joint_whitened.png").stat().st_size > 10_000


def test_imu_tk_pipeline_matches_imu_tk_on_its_own_recording(shared_data, tmp_path):
    written = run_sessions([EXAMPLES / "imu_tk_xsens.toml"], PIPELINES / "imu_tk.toml", tmp_path, quiet=True)
    cal = Calibration.from_json(written[0].read_text())
    inv_k = {"accel": [414.459, 412.01, 414.649], "gyro": [4777.96, 4764.21, 4773.66]}  # data/README.md
    for sensor, ref in inv_k.items():
        M = cal[sensor].M
        np.testing.assert_allclose(1 / np.diag(M), ref, rtol=1e-3)  # within 0.1 % of imu_tk
    T_acc = cal["accel"].M / np.diag(cal["accel"].M)[None, :]
    np.testing.assert_allclose(T_acc[np.triu_indices(3, 1)], [-0.0033593, -0.00890639, -0.0213341], atol=5e-4)
    assert np.allclose(np.tril(cal["accel"].M, -1), 0.0)  # imu_tk's gauge: T upper-triangular

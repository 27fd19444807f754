"""Method A ellipsoids with offsets beyond the radius: raw counts, hard iron > Earth's field.

The D33 = 0 form of eq. (10) (right-hand side 1) needs the origin inside the
ellipsoid; the solvers fit on centred points, so any offset is recovered.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from method_a_synth import S_ACC, G, unit_sphere
from scipy.spatial.transform import Rotation

from imupipe.cli import main
from imupipe.observations import EllipsoidObservations
from imupipe.solvers.ellipsoid_cholesky import EllipsoidCholesky, EllipsoidParams
from imupipe.solvers.mag_dip import MagDip, MagDipParams

OFFSET_DIR = np.array([0.6, -0.48, 0.64])  # unit vector: the offset reaches every axis
OFFSETS_R = [0.5, 2.0, 100.0]  # offset / radius; 100: a 16-bit accelerometer in counts
ACC_BIAS_TOL_MG = 0.3  # as test_method_a_ellipsoid: N = 200, sigma 0.5 mg
ACC_M_TOL_PPM = 1500
MAG_M_TOL = 0.002
MAG_BIAS_TOL_NT = 200.0
NOISE_MG = 0.5


@pytest.mark.parametrize("offset_r", OFFSETS_R)
def test_accel_recovers_offsets_beyond_the_radius(offset_r):
    rng = np.random.default_rng(11)
    n, lsb = 200, 4096 / G  # counts per m/s^2 (a +-8 g range at 16 bit)
    x = unit_sphere(n, rng) * G
    x[0], x[1] = [0, G, 0], [G, 0, 0]  # instrument Y up, X up
    S = S_ACC * lsb
    b = OFFSET_DIR * offset_r * 4096.0  # counts; radius 4096 counts
    sigma = NOISE_MG * 1e-3 * G * lsb
    y = x @ S.T + b + rng.normal(size=(n, 3)) * sigma
    obs = EllipsoidObservations("accel", y, np.tile(np.eye(3) * sigma**2, (n, 1, 1)),
                                np.full(n, np.nan), G, 0, 1)
    fit = EllipsoidCholesky().solve(obs, EllipsoidParams())
    bias_mg = (fit.b0 - b) / lsb / G * 1e3
    assert np.all(np.abs(bias_mg) < ACC_BIAS_TOL_MG)
    assert np.abs(fit.M @ S - np.eye(3)).max() * 1e6 < ACC_M_TOL_PPM
    sigma_mg = np.sqrt(np.diag(fit.cov))[9:] / lsb / G * 1e3
    assert np.all(np.abs(bias_mg) < 5 * sigma_mg)  # the propagated uncertainty still holds


@pytest.mark.parametrize("offset_r", OFFSETS_R)
def test_mag_recovers_hard_iron_beyond_the_field(offset_r):
    rng = np.random.default_rng(12)
    n, field, dip = 200, 50e-6, np.radians(65.0)
    B_n, g_n = np.array([np.cos(dip), -np.sin(dip), 0.0]) * field, np.array([0.0, 1.0, 0.0])
    att = Rotation.random(n, random_state=12).as_matrix()
    g = np.einsum("kji,j->ki", att, g_n)
    S = np.eye(3) + rng.normal(size=(3, 3)) * 0.03
    b = OFFSET_DIR * offset_r * field
    y = np.einsum("kji,j->ki", att, B_n) @ S.T + b + rng.normal(size=(n, 3)) * 0.05e-6
    obs = EllipsoidObservations("mag", y, np.zeros((n, 3, 3)), np.zeros(n), field, gravity=g)
    fit = MagDip().solve(obs, MagDipParams())
    assert np.abs(fit.M @ S - np.eye(3)).max() < MAG_M_TOL
    assert np.all(np.abs(fit.b0 - b) * 1e9 < MAG_BIAS_TOL_NT)
    assert abs(fit.details["dip_deg"] - 65.0) < 0.05


IMU_TK_ACC_B = np.array([33124.2, 33275.2, 32364.4])  # counts, ../shared/data/README.md
IMU_TK_ACC_SCALE = np.array([414.459, 412.01, 414.649]) * 9.81744 / G  # counts per m/s^2 at G
IMU_TK_B_TOL_COUNTS = 2.0  # 2 counts = 0.5 mg
IMU_TK_SCALE_TOL = 0.003


def test_imu_tk_xsens_runs_through_the_sphere_rig_pipeline(shared_data, tmp_path):
    """Raw counts (offset ~ 80 x the radius): method A's pipeline completes on real data and
    matches imu_tk's accelerometer. The session's turns are ~90 deg and none is the roll
    turn, so the gyro uses exact rotations instead of the small-angle sum (eq. 29)."""
    root = Path(__file__).resolve().parents[2]
    session = root / "examples" / "sessions" / "imu_tk_xsens.toml"
    small_angle = "solver_params = { exact_rotation = false, max_scale_turn_deg = 10.0 }"
    text = (root / "pipelines" / "sphere-rig.toml").read_text()
    assert small_angle in text
    pipeline = tmp_path / "sphere-rig-exact.toml"
    pipeline.write_text(text.replace(small_angle, "solver_params = { exact_rotation = true }"))
    out = tmp_path / "out"
    assert main(["run", str(session), "--pipeline", str(pipeline), "--out", str(out), "--quiet"]) == 0
    cal = json.loads((out / "imu_tk_xsens" / "calibration.json").read_text())
    assert np.all(np.abs(np.array(cal["accel"]["b0"]) - IMU_TK_ACC_B) < IMU_TK_B_TOL_COUNTS)
    scale = 1 / np.diag(np.array(cal["accel"]["M"]))
    assert np.all(np.abs(scale / IMU_TK_ACC_SCALE - 1) < IMU_TK_SCALE_TOL)
    assert "gyro" in cal

"""The magnetometer aligned to the accelerometer from a free tumble with both, no rests
(pipelines/magnetometer-accel.toml: tumble_windows -> calibrate_accel -> calibrate_mag)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from scipy.spatial.transform import Rotation
from stage_chain import run_stage

from imupipe import schemas
from imupipe.errors import SolverError
from imupipe.pipeline.config import load_pipeline
from imupipe.plugins import make_registry

G = 9.80665
B, DIP = 50e-6, 60.0
S_ACC = np.array([[1.02, 0.004, -0.003], [0.004, 0.99, 0.002], [-0.003, 0.002, 1.01]])
Q = Rotation.from_rotvec(np.radians([3.0, -1.5, 2.0])).as_matrix()  # mag chip vs accel chip
S_MAG = np.array([[1.08, 0.03, -0.02], [0.03, 0.95, 0.04], [-0.02, 0.04, 1.01]]) @ Q
B_ACC, B_MAG = np.array([0.12, -0.08, 0.2]), np.array([12e-6, -7e-6, 3e-6])


def tumble(seed=0, rate_hz=100.0, moves=150):
    """A hand tumble: 0.8 s turns at random rates, each followed by 0.4 s of slow drift."""
    rng = np.random.default_rng(seed)
    w = []
    for _ in range(moves):
        w.append(np.tile(rng.normal(0, 1.5, 3), (int(0.8 * rate_hz), 1)))
        w.append(np.tile(rng.normal(0, 0.03, 3), (int(0.4 * rate_hz), 1)))
    w = np.vstack(w) + rng.normal(0, 0.05, (sum(len(x) for x in w), 3))
    steps = Rotation.from_rotvec(w / rate_hz).as_matrix()
    R, Rs = Rotation.random(random_state=seed).as_matrix(), []
    for s in steps:
        R = R @ s
        Rs.append(R)
    Rt = np.transpose(np.array(Rs), (0, 2, 1))  # world -> body
    field = np.array([0.0, np.cos(np.radians(DIP)), -np.sin(np.radians(DIP))]) * B
    f_body = Rt @ np.array([0, 0, G]) + rng.normal(0, 0.05, (len(w), 3))  # + linear accel
    acc = f_body @ np.linalg.inv(S_ACC).T + B_ACC + rng.normal(0, 0.02, f_body.shape)
    mag = (Rt @ field) @ S_MAG.T + B_MAG + rng.normal(0, 0.1e-6, f_body.shape)
    t = (np.arange(len(w)) * 1e9 / rate_hz).astype(np.int64)

    def table(v, sid):
        return schemas.stamp(pa.table({"t_ns": t, "x": v[:, 0], "y": v[:, 1], "z": v[:, 2]}), sid)

    return {"accel": table(acc, "accel"), "gyro": table(w, "gyro"), "mag": table(mag, "mag")}


def test_mag_aligned_to_accel_from_a_tumble_without_rests():
    registry = make_registry()
    pipe = load_pipeline("magnetometer-accel", registry)
    p = {k: n.params.model_dump() for k, n in pipe.nodes.items()}
    data = tumble()
    rests = run_stage(registry, "tumble_windows", data, **p["windows"])["rests"]
    accel = run_stage(registry, "calibrate_accel", {"rests": rests}, **p["accel"])["calibration"]
    mag = run_stage(registry, "calibrate_mag", {"rests": rests, "accel": accel, "mag": data["mag"]},
                    **{**p["mag"], "field_T": B})["calibration"]
    acc_row = accel.to_pylist()[0]
    M_a = np.array(acc_row["M"]).reshape(3, 3)
    np.testing.assert_allclose(M_a, S_ACC, atol=3e-3)  # the linear acceleration is the limit
    row = mag.to_pylist()[0]
    M_m = np.array(row["M"]).reshape(3, 3)
    # the rotation of the mag chip is found: M undoes S_MAG (not only its symmetric part)
    err = Rotation.from_matrix(np.linalg.qr(M_m @ S_MAG)[0] * np.sign(np.diag(np.linalg.qr(M_m @ S_MAG)[1])))
    assert np.degrees(np.linalg.norm(err.as_rotvec())) < 0.5
    np.testing.assert_allclose(M_m @ S_MAG, np.eye(3), atol=1e-2)
    np.testing.assert_allclose(row["b0"], B_MAG, atol=0.3e-6)
    import json
    details = json.loads(row["details"]) if isinstance(row["details"], str) else row["details"]
    assert abs(details["dip_deg"] - DIP) < 0.5
    # the magnetometer alone (magcal's symmetric soft iron) cannot see the chip's rotation
    free = run_stage(registry, "calibrate_mag_free", {"mag": data["mag"]}, field_T=B)
    E = np.array(free["calibration"].to_pylist()[0]["M"]).reshape(3, 3) @ S_MAG
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(np.linalg.qr(E)[0] * np.sign(
        np.diag(np.linalg.qr(E)[1]))).as_rotvec())) > 3.0


def test_a_tumble_too_short_is_refused():
    data = {k: v.slice(0, 200) for k, v in tumble().items()}
    with pytest.raises(SolverError, match="calm windows|under 13 windows"):
        run_stage(make_registry(), "tumble_windows", data)

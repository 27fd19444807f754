"""The README's main job: `imupipe run` on the bundled simulated session, checked against its truth.

Targets are the method-A issue's accuracy targets; the example is a short session
(80 positions at 50 Hz), so this also guards the default pipeline's accuracy.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from imupipe.cli import main
from imupipe.models import Calibration
from imupipe.sim.truth import load_truth

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "standard-session.mcap"
ACC_BIAS_TOL_MG = 0.2
ACC_SHAPE_TOL_PPM = 200
GYRO_SHAPE_TOL_PPM = 300
GYRO_ACCEL_ALIGN_TOL_DEG = 0.02
MAG_SHAPE_TOL_PERCENT = 0.2
G = 9.80665


def _frame_and_shape(estimate: np.ndarray, truth_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split ``M_est S_true`` (identity if exact) into a rotation (frame choice) and the rest."""
    A = estimate @ truth_S
    U, _, Vt = np.linalg.svd(A)
    R = U @ Vt
    return R, R.T @ A


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    assert main(["run", str(EXAMPLE), "--out", str(out), "--quiet"]) == 0
    path = out / "standard-session" / "calibration.json"
    return json.loads(path.read_text()), out / "standard-session"


def test_contract_keys(result):
    doc, _ = result
    assert doc["session"].endswith("standard-session.mcap") and doc["pipeline"] == "default"
    assert doc["temperature_reference_C"] == 25.0 and doc["imupipe_version"]
    for sensor, unit in (("accel", "m/s^2"), ("gyro", "rad/s"), ("mag", "T")):
        assert doc[sensor]["units"] == unit
        assert np.shape(doc[sensor]["M"]) == (3, 3) and len(doc[sensor]["b0"]) == 3 and len(doc[sensor]["k"]) == 3


def test_recovers_truth_within_targets(result):
    doc, _ = result
    cal = Calibration.from_dict(doc)
    truth = load_truth(EXAMPLE.with_name(EXAMPLE.name + ".truth.json")).calibration

    R_acc, P_acc = _frame_and_shape(cal["accel"].M, truth["accel"].S)
    assert np.abs(cal["accel"].b0 - truth["accel"].b0).max() / G * 1e3 < ACC_BIAS_TOL_MG
    assert np.abs(P_acc - np.eye(3)).max() * 1e6 < ACC_SHAPE_TOL_PPM

    R_gyr, P_gyr = _frame_and_shape(cal["gyro"].M, truth["gyro"].S)
    assert np.abs(P_gyr - np.eye(3)).max() * 1e6 < GYRO_SHAPE_TOL_PPM
    assert _angle_deg(R_acc.T @ R_gyr) < GYRO_ACCEL_ALIGN_TOL_DEG

    _, P_mag = _frame_and_shape(cal["mag"].M, truth["mag"].S)
    # no field_T in the default pipeline: the field's absolute scale is the sensor's nominal one
    assert np.abs(P_mag / np.cbrt(np.linalg.det(P_mag)) - np.eye(3)).max() * 100 < MAG_SHAPE_TOL_PERCENT


def test_report_is_written(result):
    _, out = result
    report = (out / "report.md").read_text()
    assert "Turn validation" in report
    for link in [line.split("](")[1].rstrip(")") for line in report.splitlines() if line.startswith("![")]:
        assert (out / link).is_file(), link

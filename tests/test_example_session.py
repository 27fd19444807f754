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
from imupipe.sim.compare import calibration_errors
from imupipe.sim.truth import load_truth

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "standard-session.mcap"
ACC_BIAS_TOL_MG = 0.2
ACC_SHAPE_TOL_PPM = 200
GYRO_SHAPE_TOL_PPM = 300
GYRO_ACCEL_ALIGN_TOL_DEG = 0.02
MAG_SHAPE_TOL_PERCENT = 0.2
G = 9.80665


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

    e = calibration_errors(cal, truth, g_m_s2=G)

    assert e["accel"].bias < ACC_BIAS_TOL_MG
    assert e["accel"].shape_ppm < ACC_SHAPE_TOL_PPM
    assert e["gyro"].shape_ppm < GYRO_SHAPE_TOL_PPM
    assert e.gyro_accel_align_deg < GYRO_ACCEL_ALIGN_TOL_DEG
    # no field_T in the default pipeline: the field's absolute scale is the sensor's nominal one
    assert e["mag"].shape_scale_aside_ppm * 1e-4 < MAG_SHAPE_TOL_PERCENT


def test_report_is_written(result):
    _, out = result
    report = (out / "report.md").read_text()
    assert "Turn validation" in report
    for link in [line.split("](")[1].rstrip(")") for line in report.splitlines() if line.startswith("![")]:
        assert (out / link).is_file(), link


def test_the_per_sample_table_is_stored_as_one_batch(result):
    """Each column one array: the digest of a table of several chunks copies it whole first."""
    from pyarrow import ipc

    _, out = result
    (path,) = (out.parent / ".cache").rglob("samples.arrow")
    with ipc.open_file(path) as stored:
        assert stored.num_record_batches == 1 and stored.schema.field("sensor").type == "string"
        sensors = stored.get_batch(0).column("sensor").to_pylist()
    assert sensors[0] == "accel" and sensors[-1] == "gyro"


def test_a_warm_rerun_imports_no_solver_or_plotting_library(result):
    """Nothing to recompute (a warm batch): the rerun reads its cache and copies its exports,
    without importing SciPy, Arrow's compute kernels or matplotlib (a warm batch is then ~3 %
    of a cold one)."""
    import subprocess
    import sys

    _, out = result
    code = ("import sys\n"
            "from imupipe.cli import main\n"
            f"assert main(['run', {str(EXAMPLE)!r}, '--out', {str(out.parent)!r}, '--quiet']) == 0\n"
            "heavy = [m for m in ('scipy', 'pyarrow.compute', 'matplotlib') if m in sys.modules]\n"
            "assert not heavy, heavy\n")
    proc = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]

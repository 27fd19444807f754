"""Silent wrong answers of issues 10 and 12 turned into refusals or verdicts.

Built from one short simulated gimbal session (``faulty_synth``): parameter unit
slips, an initial rest that is not still, streams in g / deg/s / uT / kelvin under
SI names (exit 2, one line naming the unit), sections spliced together (fail), a
gap and a shock inside a motion (the turn left out, the calibration as the clean
one's, warn).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

import faulty_synth as F
from imupipe.cli import main
from imupipe.diagnosis import events as ev
from imupipe.errors import ConfigError, ReaderError
from imupipe.models import Calibration
from imupipe.pipeline.config import load_pipeline
from imupipe.plugins import make_registry
from imupipe.sim.api import simulate_recording, write_csv
from imupipe.stages.screen import check_units

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
GYRO_AGREEMENT = 5.0  # the faulty run's gyro M within this many of its own sigma of the clean one


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    folder = tmp_path_factory.mktemp("screen")
    cols = F.clean_gimbal(folder / "clean.csv")
    pipeline = F.fast_pipeline(folder, PIPELINES)
    out = folder / "out"
    assert main(["run", str(folder / "clean.csv"), "--pipeline", str(pipeline), "--out", str(out),
                 "--quiet"]) == 0
    cal = Calibration.from_json((out / "clean" / "calibration.json").read_text())
    return {"folder": folder, "cols": cols, "pipeline": pipeline, "cal": cal}


def run(clean, name: str, cols, capsys) -> tuple[int, str, str, Calibration | None]:
    """Exit status, stdout, stderr (or, after a success, the screening's warnings), calibration."""
    path = F.write(clean["folder"] / f"{name}.csv", cols)
    out = clean["folder"] / "out"
    code = main(["run", str(path), "--pipeline", str(clean["pipeline"]), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    if code != 0:
        return code, captured.out, captured.err, None
    warned = json.loads((out / name / "run.json").read_text())["stages"]["screen"]["warnings"]
    return code, captured.out, " ".join(warned), Calibration.from_json((out / name / "calibration.json").read_text())


def streams(cols) -> dict:
    t = (cols["t_ns"] - cols["t_ns"][0]) * 1e-9
    return {s: (t, np.column_stack([cols[f"{s}_{a}"] for a in "xyz"])) for s in ("accel", "gyro")}


def assert_gyro_as_clean(cal: Calibration, clean_cal: Calibration) -> None:
    M, M0 = cal["gyro"].M, clean_cal["gyro"].M
    sigma = np.asarray(cal["gyro"].details["sigma_M"])
    assert np.all(np.abs(M - M0) < GYRO_AGREEMENT * sigma + 1e-12), np.abs(M - M0) / sigma


# --------------------------------------------------------------------------- detectors


def test_the_clean_session_has_no_events(clean):
    assert ev.detect(streams(clean["cols"])) == []


def test_detectors_find_each_fault_where_it_is(clean):
    cols = clean["cols"]
    spliced, joins = F.splice(cols)
    found = [e for e in ev.detect(streams(spliced)) if e.kind == "splice"]
    assert found and all(min(abs(e.window[1] - j) for j in joins) < 0.02 for e in found)
    holed, t_gaps = F.gap(cols)
    gaps = ev.detect(streams(holed))
    assert {e.kind for e in gaps} == {"gap"} and {e.sensor for e in gaps} == {"accel", "gyro"}
    assert np.allclose(sorted({round(e.window[0], 3) for e in gaps}), t_gaps, atol=0.02)
    knocked, t_shock = F.shock(cols)
    shocks = ev.detect(streams(knocked))
    assert {e.kind for e in shocks} == {"shock"} and {e.sensor for e in shocks} == {"accel", "gyro"}
    assert all(e.window[0] < t_shock < e.window[1] for e in shocks)


# --------------------------------------------------------------------------- refusals (exit 2)


@pytest.mark.parametrize("key, value, unit", [
    ("g_m_s2", "98.1", "in m/s^2"), ("g_m_s2", "1.0", "in m/s^2"), ("field_T", "50.0", "in T"),
])
def test_parameter_unit_slips_are_refused(key, value, unit, tmp_path):
    text = (PIPELINES / "default.toml").read_text()
    if key == "field_T":
        text = text.replace('solver = "ellipsoid_dip"', f'solver = "ellipsoid_dip"\nfield_T = {value}')
    else:
        text = text.replace("g_m_s2 = 9.80665", f"g_m_s2 = {value}")
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    shown = value.rstrip("0").rstrip(".")
    with pytest.raises(ConfigError, match=rf"{key}: {shown} is not .*a unit slip\? give it {re.escape(unit)}"):
        load_pipeline(bad, make_registry())


def test_an_initial_rest_that_is_not_still_is_refused(clean, capsys):
    """imu_tk's pipeline measures the noise over the first 50 s, assumed still: here they are not."""
    rec, _ = simulate_recording("gimbal", {}, 4, grid_deg=60.0, n_rotations=2, rest_s=3.5, step_s=8.0)
    path = clean["folder"] / "moving.csv"
    write_csv(path, rec)
    code = main(["run", str(path), "--pipeline", str(PIPELINES / "imu_tk.toml"), "--out",
                 str(clean["folder"] / "out"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "moving.csv" in err and "the first 50 s are not still" in err
    assert "set initial_rest_s = 0" in err


@pytest.mark.parametrize("sensor, factor, unit", [
    ("accel", 1 / F.G, "the data look like g"), ("gyro", 180 / np.pi, "the data look like deg/s"),
])
def test_si_names_on_other_units_are_refused(clean, capsys, sensor, factor, unit):
    code, _, err, _ = run(clean, f"in_{sensor}", F.units(clean["cols"], sensor, factor), capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"in_{sensor}.csv" in err and unit in err


def _table(values: np.ndarray, columns=("x", "y", "z")) -> pa.Table:
    cols = {"t_ns": np.arange(len(values), dtype=np.int64) * 10_000_000}
    cols.update({c: values[:, i] for i, c in enumerate(columns)} if values.ndim == 2 else {columns[0]: values})
    return pa.table(cols)


@pytest.mark.parametrize("stream, factor, unit", [
    ("mag", 1e6, "uT"), ("mag", 1e4, "gauss"), ("temperature", None, "kelvin"), ("accel", 1e3 / F.G, "mg"),
])
def test_magnitudes_name_the_unit(clean, stream, factor, unit):
    cols = clean["cols"]
    if stream == "temperature":
        table = _table(cols["temperature"] + 273.15, ("temperature",))
    else:
        table = _table(np.column_stack([cols[f"{stream}_{a}"] for a in "xyz"]) * factor)
    with pytest.raises(ReaderError, match=f"the data look like {unit};"):
        check_units({stream: table})
    counts = table.replace_schema_metadata({b"imupipe.raw_unit": b"counts"})
    check_units({stream: counts})  # a declared raw unit is not judged


# --------------------------------------------------------------------------- left out, judged


def test_a_spliced_recording_fails_and_is_not_fitted_as_turns(clean, capsys):
    spliced, joins = F.splice(clean["cols"])
    code, out, err, cal = run(clean, "spliced", spliced, capsys)
    assert code == 0 and "turns left out of the fits" in err
    assert "verdict: fail" in out and "splices in the recording" in out
    assert_gyro_as_clean(cal, clean["cal"])  # without the screen: 40 % off (gyro scale)


def test_a_gap_inside_a_motion_is_not_integrated_across(clean, capsys):
    holed, _ = F.gap(clean["cols"])
    code, out, err, cal = run(clean, "gap", holed, capsys)
    assert code == 0 and "3 of 35 turns left out of the fits: they hold 3 gaps" in err
    assert "verdict: warn" in out and "gaps in the recording" in out
    assert_gyro_as_clean(cal, clean["cal"])


def test_a_shock_inside_a_motion_does_not_distort_the_gyro(clean, capsys):
    knocked, _ = F.shock(clean["cols"])
    code, out, err, cal = run(clean, "shock", knocked, capsys)
    assert code == 0 and "1 of 35 turns left out of the fits: they hold 1 shock" in err
    assert "verdict: warn" in out and "shocks in the recording" in out
    assert_gyro_as_clean(cal, clean["cal"])  # without the screen: 3400 ppm off

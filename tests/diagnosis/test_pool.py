"""``imupipe diagnose`` on several recordings of one unit: the pooled diagnosis stays quiet on nulls,
names an effect no single session can see, and refuses recordings of different units."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl

from imupipe.cli import main
from imupipe.diagnosis.select import VISIBLE_MIN
from imupipe.pipeline.pooled import diagnose_sessions
from imupipe.sim.api import simulate_recording, write_csv
from imupipe.sim.sensor import default_imu

GIMBAL = Path(__file__).resolve().parents[2] / "pipelines" / "gimbal-optimization.toml"
PPM = [8.0, -8.0, 8.0]  # ppm/degC: several times the pooled minimum detectable size (~1)
PPM_TOL = 2.0


def _unit(seed: int = 7):
    imu = default_imu(np.random.default_rng([seed, 2]))
    return imu.model_copy(update={"accel": imu.accel.model_copy(update={"bias_rw": 1e-5}),
                                  "gyro": imu.gyro.model_copy(update={"bias_rw": 1e-6}),
                                  "thermal": imu.thermal.model_copy(update={"readout_quantum_C": 0.125})})


def _session(folder: Path, unit, die_C: float, seed: int, effects: dict) -> Path:
    """A short gimbal session of ``unit`` with its die held at ``die_C`` (warm before power-on)."""
    imu = unit.model_copy(update={"thermal": unit.thermal.model_copy(
        update={"ambient_C": die_C - unit.thermal.self_heating_C, "initial_C": die_C})})
    rec, _ = simulate_recording("gimbal", effects, seed, imu=imu, env={"gravity_m_s2": 9.80665},
                                grid_deg=60.0, n_rotations=6, rest_s=2.0)
    path = folder / f"unit-{die_C:g}C-{'-'.join(effects) or 'null'}.csv"
    write_csv(path, rec)
    return path


def _visible(doc: dict, effect: str, sensor: str) -> float:
    return max(t["visible_fraction"] for t in doc["tested"] if (t["effect"], t["sensor"]) == (effect, sensor))


def test_pooled_null_sessions_of_one_unit_give_no_finding(tmp_path):
    unit = _unit()
    paths = [_session(tmp_path, unit, T, 100 + k, {}) for k, T in enumerate((15.0, 45.0))]
    _, pooled = diagnose_sessions(paths, GIMBAL, tmp_path / "out", quiet=True)
    assert pooled == tmp_path / "out" / "pooled" / "diagnosis.json"
    doc = json.loads(pooled.read_text())
    assert doc["findings"] == [] and doc["sessions"] == [p.stem for p in paths]
    # the calibration is shared, the turn-on biases are not
    assert doc["shared"] == ["S_a", "M_g"] and doc["per_session"] == ["b_a", "b_g"]
    # a scale that changes with temperature: invisible at one temperature, visible across two
    for p in paths:
        own = json.loads((tmp_path / "out" / p.stem / "diagnosis.json").read_text())
        assert own["findings"] == []
        assert _visible(own, "accel_scale_temperature", "accel") < VISIBLE_MIN
    assert _visible(doc, "accel_scale_temperature", "accel") > 0.5
    # a bias that changes with temperature stays hidden: each session's turn-on bias takes it
    assert ("bias_temperature_nonlinear", "accel") in {(n["effect"], n["sensor"]) for n in doc["not_identifiable"]}
    report = (pooled.parent / "report.md").read_text()
    assert "| accel_scale_temperature/accel | 0.000 | 0.000 |" in report


def test_an_effect_no_single_session_can_see_is_named_when_pooled(tmp_path, capsys):
    unit = _unit()
    effect = {"accel_scale_temperature": {"ppm_per_C": PPM}}
    paths = [_session(tmp_path, unit, T, 200 + k, effect) for k, T in enumerate((15.0, 45.0))]
    out = tmp_path / "out"
    assert main(["diagnose", *map(str, paths), "--pipeline", str(GIMBAL), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    for p in paths:  # each session alone: not identifiable, not found
        own = json.loads((out / p.stem / "diagnosis.json").read_text())
        assert "accel_scale_temperature" in {n["effect"] for n in own["not_identifiable"]}
        assert not [f for f in own["findings"] if f["effect"] == "accel_scale_temperature"]
    doc = json.loads((out / "pooled" / "diagnosis.json").read_text())
    assert str(out / "pooled" / "diagnosis.json") in printed
    assert [f["effect"] for f in doc["findings"]] == ["accel_scale_temperature"], doc["findings"]
    f = doc["findings"][0]
    np.testing.assert_allclose(f["parameters"]["ppm_per_C"], PPM, atol=PPM_TOL)
    assert f["heldout_rms_after"] < f["heldout_rms_before"] and f["heldout_z"] > 1.645
    assert set(f["window_sessions"]) <= {p.stem for p in paths} and len(f["windows"]) == len(f["window_sessions"])


def test_recordings_of_different_sensors_are_refused_naming_the_file(tmp_path, capsys):
    unit = _unit()
    rec, _ = simulate_recording("gimbal", {}, 1, imu=unit, grid_deg=90.0, n_rotations=2, rest_s=1.0)
    full, bare = tmp_path / "full.csv", tmp_path / "no-mag.csv"
    write_csv(full, rec)
    pl.read_csv(full).drop(["mag_x", "mag_y", "mag_z"]).write_csv(bare)
    assert main(["diagnose", str(full), str(bare), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bare}: records accel, gyro, {full} accel, gyro, mag" in err
    assert not (tmp_path / "o" / "full").exists()  # refused before anything was calibrated

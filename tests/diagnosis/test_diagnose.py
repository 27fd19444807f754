"""``imupipe diagnose`` on short simulated gimbal sessions: it names and fits a concealed lever
arm, proves it on held-out motions, and stays quiet on the same session without it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from imupipe.cli import main
from imupipe.pipeline.api import run_sessions
from imupipe.sim.api import simulate_recording, write_csv

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
GIMBAL = PIPELINES / "gimbal-optimization.toml"
LEVER_M = [0.03, -0.02, 0.01]


def _session(folder: Path, effects: dict, seed: int = 5) -> Path:
    rec, _ = simulate_recording("gimbal", effects, seed, env={"gravity_m_s2": 9.80665},
                                grid_deg=45.0, n_rotations=30, rest_s=3.0)
    path = folder / f"gimbal-{'-'.join(effects) or 'null'}.csv"
    write_csv(path, rec)
    return path


def _diagnosis(tmp_path: Path, effects: dict) -> tuple[dict, dict]:
    path = _session(tmp_path, effects)
    run_sessions([path], GIMBAL, tmp_path / "out", quiet=True, diagnose=True)
    folder = tmp_path / "out" / path.stem
    return (json.loads((folder / "diagnosis.json").read_text()),
            json.loads((folder / "residual_map.json").read_text()))


def test_a_concealed_lever_arm_is_named_fitted_and_proved_on_held_out_motions(tmp_path):
    doc, rmap = _diagnosis(tmp_path, {"lever_arm": {"r_m": LEVER_M}})
    # the attitude nuisance bends towards the misfit, so gyro motion cells light up too, but
    # the accelerometer in motion carries most of it and ranks first
    top = rmap["cells"][0]
    assert top["flagged"] and (top["sensor"], top["regime"]) == ("accel", "motion")
    named = [f for f in doc["findings"] if f["effect"] == "lever_arm"]
    assert len(named) == 1, doc["findings"]
    f = named[0]
    assert (f["sensor"], f["regime"]) == ("accel", "motion")
    np.testing.assert_allclose(f["parameters"]["r_m"], LEVER_M, atol=0.004)
    # the noise's share of the error: far below the one-step linearisation's at 350x the minimum
    # detectable size (docs/residual-map.md)
    sd = np.asarray(f["parameters_sd"]["r_m"])
    assert np.all(sd > 1e-6) and np.all(sd < 1e-4)
    assert f["heldout_rms_after"] < f["heldout_rms_before"]
    sig = f["significance"]  # the wild bootstrap's smallest p with 999 draws, and chi-square's
    assert sig["p_value"] == 1 / 1000 and sig["p_value_asymptotic"] < 1e-6 and sig["delta_bic"] < 0
    assert f["windows"] and f["explanation"]
    assert not [g for g in doc["findings"] if g["effect"] not in ("lever_arm", "unknown")]
    cal = json.loads((tmp_path / "out" / "gimbal-lever_arm" / "calibration.json").read_text())
    assert [t["effect"] for t in cal["model_terms"]] == ["lever_arm"]
    report = (tmp_path / "out" / "gimbal-lever_arm" / "report.md").read_text()
    assert "**lever_arm**" in report and "diagnosis_heldout.png" in report


def test_diagnose_stays_quiet_without_omitted_physics(tmp_path):
    doc, rmap = _diagnosis(tmp_path, {})
    assert doc["findings"] == []
    assert not [c for c in rmap["cells"] if c["flagged"]]
    for block in rmap["blocks"]:  # the whitened residuals are unit-variance where the model holds
        assert abs(block["chi2_per_dof"] - 1) < 4 * np.sqrt(2 / block["dof"]) + 0.05, block
    assert {t["effect"] for t in doc["tested"]} >= {"lever_arm", "accel_gyro_time_offset", "gyro_g_sensitivity"}
    assert all(0 <= t["visible_fraction"] <= 1 for t in doc["tested"])


def test_diagnose_refuses_a_pipeline_without_a_residual_map(tmp_path, capsys):
    path = tmp_path / "session.csv"
    path.write_text("t,ax\n")
    pipeline = tmp_path / "p.toml"
    pipeline.write_text('name = "bare"\n[stages.rests]\nuses = "segment_stillness"\n'
                        'inputs = { accel = "session.accel", gyro = "session.gyro" }\n')
    assert main(["diagnose", str(path), "--pipeline", str(pipeline), "--out", str(tmp_path / "o")]) == 2
    assert "no map_residuals stage" in capsys.readouterr().err


def test_earth_rate_is_reported_as_the_naming_trap_it_is_at_rest(tmp_path):
    # at rest Earth's vertical rate is G = (Omega sin(lat) / g) I: without the latitude neither is
    # named; the one-column fit gives the latitude it would be
    doc, _ = _diagnosis(tmp_path, {"earth_rotation": {"latitude_deg": 55.75}})
    gyro = [f for f in doc["findings"] if f["sensor"] == "gyro" and "candidates" in f["parameters"]]
    assert [f["parameters"]["candidates"] for f in gyro] == [["earth_rotation", "gyro_g_sensitivity"]], doc["findings"]
    assert 40 < gyro[0]["parameters"]["earth_rotation"]["latitude_deg"] < 75
    assert not [f for f in doc["findings"] if f["effect"] in ("earth_rotation", "gyro_g_sensitivity")]

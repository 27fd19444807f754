"""Ferraris / six poses + known-angle turns (pipelines/ferraris.toml): imucal's protocol."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from imupipe import cli

REPO = Path(__file__).resolve().parents[2]
MANIFEST = REPO / "examples" / "sessions" / "imucal_ferraris.toml"
# imucal's published calibration of its example session (shared/data/README.md)
IMUCAL = {"accel_scale": [0.99675, 1.00244, 1.02340], "accel_bias": [0.537, -0.616, 0.399],
          "gyro_scale": [1.02792, 0.98243, 0.99831], "gyro_bias_dps": [-0.600, -0.370, 0.059]}


def _run(tmp_path, session, *extra) -> tuple[int, Path]:
    out = tmp_path / "out"
    code = cli.main(["run", str(session), "--pipeline", "ferraris", "--out", str(out), "--quiet",
                     *extra])
    return code, out


@pytest.mark.parametrize("g_sensitivity", [False, True])
def test_imucal_session_reproduces_imucal(tmp_path, shared_data, g_sensitivity, capsys):
    code, out = _run(tmp_path, MANIFEST, "--set", "ferraris.g_m_s2=9.81", "--set",
                     f"ferraris.solver_params.g_sensitivity={str(g_sensitivity).lower()}")
    assert code == 0, capsys.readouterr().err
    doc = json.loads((out / "imucal_ferraris" / "calibration.json").read_text())
    acc, gyr = doc["accel"], doc["gyro"]
    assert acc["sections_source"] == "section list" and gyr["turn_angle_deg"] == -360.0
    np.testing.assert_allclose(acc["K"], IMUCAL["accel_scale"], atol=6e-6)
    np.testing.assert_allclose(acc["b0"], IMUCAL["accel_bias"], atol=6e-4)
    np.testing.assert_allclose(np.degrees(gyr["b0"]), IMUCAL["gyro_bias_dps"], atol=6e-4)
    # imucal removes the gyro g-sensitivity (eq. 9) before the turns; without it, 3e-5 apart
    np.testing.assert_allclose(gyr["K"], IMUCAL["gyro_scale"], atol=6e-6 if g_sensitivity else 6e-5)
    # imucal's own calibrated rows (its regression snapshot): the accelerometer is the same map
    raw = np.genfromtxt(shared_data / "imucal" / "example_ferraris_session.csv", delimiter=",",
                        names=True)[:50]
    ref = np.genfromtxt(shared_data / "imucal" / "ferraris_example.csv", delimiter=",", names=True)
    y = np.column_stack([raw[f"acc_{a}"] for a in "xyz"])
    mine = (y - acc["b0"]) @ np.array(acc["M"]).T
    np.testing.assert_allclose(mine, np.column_stack([ref[f"acc_{a}"] for a in "xyz"]), atol=1e-9)


def test_mislabelled_or_missing_sections_are_refused(tmp_path, shared_data, capsys):
    sections = json.loads((shared_data / "imucal" / "example_ferraris_session_list.json").read_text())
    sections["x_p"], sections["y_p"] = sections["y_p"], sections["x_p"]
    (tmp_path / "swapped.json").write_text(json.dumps(sections))
    text = MANIFEST.read_text().replace("../../../shared/data/imucal/", f"{shared_data}/imucal/")
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "session.toml").write_text(
        text.replace(f"{shared_data}/imucal/example_ferraris_session_list.json",
                     str(tmp_path / "swapped.json")))
    code, _ = _run(tmp_path, tmp_path / "a" / "session.toml")
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "pose 'x_p' (section list) has gravity 88 deg from +x" in err and "mislabelled" in err

    # a pose section running 2 s into the motion after it (gravity still within 10 deg)
    sections["x_p"], sections["y_p"] = sections["y_p"], sections["x_p"]
    z_a = dict(sections["z_a"])
    sections["z_a"] = {"start": z_a["start"], "end": 6200}
    (tmp_path / "swapped.json").write_text(json.dumps(sections))
    code, _ = _run(tmp_path, tmp_path / "a" / "session.toml")
    err = capsys.readouterr().err
    assert code == 2 and "pose 'z_a' (section list) is not at rest" in err
    sections["z_a"] = z_a
    sections["x_p"], sections["y_p"] = sections["y_p"], sections["x_p"]

    del sections["z_rot"]
    sections["x_p"], sections["y_p"] = sections["y_p"], sections["x_p"]
    (tmp_path / "swapped.json").write_text(json.dumps(sections))
    code, _ = _run(tmp_path, tmp_path / "a" / "session.toml")
    err = capsys.readouterr().err
    assert code == 2 and "the section list lacks z_rot" in err


def test_simulated_ferraris_without_sections(tmp_path, capsys):
    from imupipe.sim.api import simulate

    path = tmp_path / "ferraris.mcap"
    simulate("ferraris", {}, 3, path, True, params={"pose_s": 4.0, "turn_s": 5.0})
    truth = json.loads(Path(f"{path}.truth.json").read_text())
    g = truth["environment"]["g_m_s2"]
    code, out = _run(tmp_path, path, "--set", f"ferraris.g_m_s2={g}")
    assert code == 0, capsys.readouterr().err
    doc = json.loads((out / "ferraris" / "calibration.json").read_text())
    for sensor in ("accel", "gyro"):
        assert doc[sensor]["sections_source"] == "stillness segmentation"
        M, M_true = np.array(doc[sensor]["M"]), np.array(truth["calibration"][sensor]["M"])
        np.testing.assert_allclose(M, M_true, atol=3e-4)  # earth rate and warm-up drift remain
    np.testing.assert_allclose(doc["gyro"]["b0"], truth["calibration"]["gyro"]["b0"], atol=1e-3)


def test_a_simulated_ferraris_null_is_diagnosed_quiet(tmp_path, capsys):
    """The pipeline's segmentation is not given the temperature: the map takes the rests' from the
    stream, so it refits the temperature coefficients the Ferraris calibration leaves out (a
    self-heating unit's bias follows its temperature, which was named a warm-up transient)."""
    from imupipe.sim.api import simulate

    path = tmp_path / "ferraris.mcap"
    simulate("ferraris", {}, 3, path, True, params={"pose_s": 4.0, "turn_s": 5.0})
    g = json.loads(Path(f"{path}.truth.json").read_text())["environment"]["g_m_s2"]
    out = tmp_path / "out"
    code = cli.main(["diagnose", str(path), "--pipeline", "ferraris", "--set", f"ferraris.g_m_s2={g}",
                     "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().err
    assert json.loads((out / "ferraris" / "diagnosis.json").read_text())["findings"] == []


def _sim_inputs(seed=3):
    """A simulated Ferraris session's tables and its section list from the truth segments."""
    import pyarrow as pa

    from imupipe import schemas
    from imupipe.sim.api import simulate_recording

    rec, truth = simulate_recording("ferraris", seed=seed, pose_s=4.0, turn_s=5.0)
    dev = rec.device()
    t0 = dev["accel"].column("t_ns").to_numpy()[0]
    segs = [s for s in truth.data["segments"] if s["label"] in ("pose", "ferraris_turn")]
    names = ["x_p", "x_rot", "x_p2", "x_a", "y_p", "y_rot", "y_p2", "y_a", "z_p", "z_rot", "z_p2", "z_a"]
    rows = [(n, int(t0 + s["t_start_s"] * 1e9), int(t0 + s["t_end_s"] * 1e9))
            for n, s in zip(names, segs, strict=True) if not n.endswith("2")]
    table = schemas.stamp(pa.table({
        "name": [r[0] for r in rows], "t_start_ns": [r[1] for r in rows],
        "t_end_ns": [r[2] for r in rows], "start": [0] * len(rows), "end": [0] * len(rows),
        "stream": ["accel"] * len(rows)}), "sections")
    return {"accel": dev["accel"], "gyro": dev["gyro"], "sections": table}, json.loads(truth.to_json())


def test_sections_path_on_simulated_data_and_a_gap_inside_a_turn_is_refused():
    from stage_chain import run_stage

    from imupipe.errors import SolverError
    from imupipe.plugins import make_registry

    inputs, truth = _sim_inputs()
    registry = make_registry()
    g = truth["environment"]["g_m_s2"]
    out = run_stage(registry, "calibrate_ferraris", inputs, g_m_s2=g)
    rows = {r["sensor"]: r for r in out["calibration"].to_pylist()}
    for sensor in ("accel", "gyro"):
        np.testing.assert_allclose(np.array(rows[sensor]["M"]).reshape(3, 3),
                                   truth["calibration"][sensor]["M"], atol=3e-4)
    # 1.5 s of gyro samples lost in the middle of the y turn: not integrated across
    gyro = inputs["gyro"]
    t = gyro.column("t_ns").to_numpy()
    y_rot = next(r for r in inputs["sections"].to_pylist() if r["name"] == "y_rot")
    mid = (y_rot["t_start_ns"] + y_rot["t_end_ns"]) // 2
    keep = np.abs(t - mid) > 0.75e9
    with pytest.raises(SolverError, match=r"turn 'y_rot' has a 1\.5\d* s gap"):
        run_stage(registry, "calibrate_ferraris", {**inputs, "gyro": gyro.filter(keep)}, g_m_s2=g)

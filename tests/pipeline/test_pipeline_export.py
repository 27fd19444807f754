"""``imupipe run --export`` and ``imupipe export RUN_DIR``: files in DIR/<session>/export/."""

from __future__ import annotations

import json

import numpy as np
import pytest

import imupipe.formats
from imupipe import cli
from imupipe.models import Calibration
from imupipe.pipeline import api
from imupipe.pipeline import export as export_api


@pytest.fixture
def registry(toy_registry, monkeypatch):
    registry, _ = toy_registry(imupipe.formats)
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    monkeypatch.setattr("imupipe.plugins.make_registry", lambda *a, **k: registry)
    return registry


def run(session, pipeline, out, *extra):
    return cli.main(["run", str(session), "--pipeline", str(pipeline), "--out", str(out),
                     "--quiet", *extra])


def test_run_exports_and_export_rewrites(tmp_path, registry, toy_pipeline, session, capsys):
    out = tmp_path / "out"
    assert run(session, toy_pipeline, out, "--export", "imu_tk,px4", "--export", "kalibr") == 0
    folder = out / "s1" / "export"
    assert sorted(p.name for p in folder.iterdir()) == [
        "imu_tk_acc.calib", "imu_tk_gyro.calib", "imu_tk_mag.calib", "kalibr_imu.yaml",
        "px4.params"]
    # the exported offsets are calibration.json's biases
    cal = Calibration.from_json((out / "s1" / "calibration.json").read_text())
    params = {r.split("\t")[2]: float(r.split("\t")[3])
              for r in (folder / "px4.params").read_text().splitlines() if not r.startswith("#")}
    np.testing.assert_allclose([params[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"], cal["gyro"].b0,
                               rtol=1e-15)
    # the run recorded what exporters need: the stream rates
    facts = json.loads((out / "s1" / "run.json").read_text())["stream_facts"]
    assert facts["accel"]["rate_hz"] == pytest.approx(100.0)
    # a later `imupipe export` of the same run folder writes the same px4 file, and only
    # what it is asked for: export/ always matches calibration.json
    before = (folder / "px4.params").read_text()
    capsys.readouterr()
    assert cli.main(["export", str(out / "s1"), "--format", "px4"]) == 0
    assert capsys.readouterr().out.strip() == str(folder / "px4.params")
    assert (folder / "px4.params").read_text() == before
    assert sorted(p.name for p in folder.iterdir()) == ["px4.params"]
    # a rerun without --export clears the folder
    assert run(session, toy_pipeline, out) == 0
    assert not folder.exists()


def test_unknown_format_is_refused_before_anything_runs(tmp_path, registry, toy_pipeline,
                                                         session, capsys):
    assert run(session, toy_pipeline, tmp_path / "out", "--export", "px4,qgc") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown format 'qgc'; known: ardupilot, imu_calib" in err
    assert not (tmp_path / "out" / "s1").exists()


def test_export_of_a_folder_without_calibration_exits_2(tmp_path, registry, capsys):
    assert cli.main(["export", str(tmp_path), "--format", "kalibr"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no calibration.json here" in err
    (tmp_path / "calibration.json").write_text("{not json")
    assert cli.main(["export", str(tmp_path), "--format", "kalibr"]) == 2
    assert "calibration.json: not a readable calibration" in capsys.readouterr().err


def test_format_the_data_cannot_fill_exits_2_and_keeps_the_calibration(tmp_path, registry,
                                                                       capsys):
    """Raw counts cannot become PX4 parameters: one line, exit 2, calibration.json stays."""
    run_dir = tmp_path / "out" / "s1"
    run_dir.mkdir(parents=True)
    doc = {"session": "s.toml", "pipeline": "p",
           "accel": {"M": np.eye(3).tolist(), "b0": [32768.0] * 3, "k": [0.0] * 3,
                     "units": "m/s^2", "raw_units": "counts"}}
    (run_dir / "calibration.json").write_text(json.dumps(doc))
    assert cli.main(["export", str(run_dir), "--format", "imu_tk,px4"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot export to PX4: raw values are accel in counts" in err
    assert (run_dir / "calibration.json").is_file()
    assert not (run_dir / "export").exists()  # imu_tk's files are not left alone
    assert export_api.format_names(registry) == ["ardupilot", "imu_calib", "imu_tk", "kalibr",
                                                 "px4"]

"""--set STAGE.PARAM=VALUE, --pipeline NAME, --device and `imupipe pipelines` (contracts.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pipeline_toys import ArrowSessionReader, status_lines, write_session

from imupipe import cli
from imupipe.errors import ConfigError
from imupipe.pipeline import api
from imupipe.pipeline.config import load_pipeline, parse_override, shipped_pipelines
from imupipe.pipeline.api import batch, run_sessions, status


def test_set_overrides_a_param_and_a_solver_param(tmp_path, toy_registry, toy_pipeline):
    registry, _ = toy_registry()
    p = load_pipeline(toy_pipeline, registry, ["scaled.factor=2.5", "mag.solver_params.scale=3"])
    assert p.nodes["scaled"].params.factor == 2.5
    assert p.nodes["mag"].solver.params.scale == 3.0
    assert p.overrides == ("scaled.factor=2.5", "mag.solver_params.scale=3")
    assert load_pipeline(toy_pipeline, registry, ['input.device="right"']).device == "right"


@pytest.mark.parametrize(
    ("item", "expected"),
    [
        ("scaeld.factor=2", "--set scaeld.factor=2: no stage 'scaeld' in "),
        ("scaled.factr=2", "stage 'scaled' (toy_scale) has no parameter 'factr'; did you mean 'factor'?"),
        ("scaled.factor", "expected STAGE.PARAM=VALUE"),
        ("factor=2", "expected STAGE.PARAM=VALUE"),
        ("input.devise=x", "[input] has no key 'devise'"),
        ("scaled.factor=[1, 2]", "stages.scaled.params.factor: "),  # validated like the file
    ],
)
def test_set_errors_name_the_override(tmp_path, toy_registry, toy_pipeline, item, expected):
    registry, _ = toy_registry()
    with pytest.raises(ConfigError) as info:
        load_pipeline(toy_pipeline, registry, [item])
    assert expected in str(info.value) and "\n" not in str(info.value)


def test_override_values_are_toml_else_bare_strings():
    assert parse_override("a.b=9.81") == (["a", "b"], 9.81)
    assert parse_override("a.b=true") == (["a", "b"], True)
    assert parse_override("a.b=[1, 2]") == (["a", "b"], [1, 2])
    assert parse_override("a.b=ellipsoid_svd") == (["a", "b"], "ellipsoid_svd")
    assert parse_override("a.s.c={ x = 1 }") == (["a", "s", "c"], {"x": 1})


def test_cli_set_reaches_run_and_status_and_bad_set_exits_2(
    tmp_path, toy_registry, toy_pipeline, session, monkeypatch, capsys
):
    registry, counter = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    out = tmp_path / "out"
    base = ["--pipeline", str(toy_pipeline), "--out", str(out), "--quiet"]
    assert cli.main(["run", str(session), *base, "--set", "scaled.factor=2.0"]) == 0
    run = json.loads((out / "s1" / "run.json").read_text())
    assert run["pipeline"]["overrides"] == ["scaled.factor=2.0"]
    capsys.readouterr()
    # status with the same --set: fresh; without: the param differs from what ran
    assert cli.main(["status", str(session), *base, "--set", "scaled.factor=2.0"]) == 0
    assert set(status_lines(capsys.readouterr().out).values()) == {"fresh"}
    lines = status_lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["scaled"] == "stale param factor changed 2.0 -> 1.0"
    # status with no --pipeline replays the overrides recorded in run.json
    text = status([], None, out, registry=registry)
    assert "with --set scaled.factor=2.0" in text.splitlines()[0]
    assert set(status_lines(text).values()) == {"fresh"}
    assert cli.main(["run", str(session), *base, "--set", "nope.factor=1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no stage 'nope'" in err and "scaled" in err


def test_batch_takes_set(tmp_path, toy_registry, toy_pipeline, session, capsys):
    registry, _ = toy_registry()
    from pipeline_toys import TOY_SPEC

    out = tmp_path / "out"
    failures = batch([str(session)], toy_pipeline, out, jobs=1, quiet=True, plugins=TOY_SPEC,
                     overrides=["scaled.factor=2.0"])
    assert failures == []
    run = json.loads((out / "s1" / "run.json").read_text())
    assert run["pipeline"]["overrides"] == ["scaled.factor=2.0"]


def test_pipeline_by_name_and_pipelines_listing(tmp_path, capsys, toy_registry):
    shipped = shipped_pipelines()
    assert {"default", "imu_tk", "magnetometer", "ferraris"} <= set(shipped)
    from imupipe.plugins import make_registry

    registry = make_registry()
    assert load_pipeline("imu_tk", registry).path == shipped["imu_tk"]
    with pytest.raises(ConfigError, match="no such pipeline file, nor a shipped pipeline"):
        load_pipeline("imu-tk", registry)
    assert cli.main(["pipelines"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(shipped)
    for line, name in zip(lines, shipped, strict=True):
        assert line.startswith(name) and len(line.split(None, 1)[1]) > 10


def test_calibrate_pipeline_is_the_default_without_its_map():
    """Shipped for archives that want the calibration alone: it must not drift from the default."""
    import tomllib

    shipped = shipped_pipelines()
    default, calibrate = (tomllib.loads(shipped[n].read_text()) for n in ("default", "calibrate"))
    map_stages = [k for k, v in default["stages"].items() if v["uses"] == "map_residuals"]
    assert map_stages and calibrate["stages"] == {
        k: v for k, v in default["stages"].items() if k not in map_stages}
    assert calibrate["export"] == {kind: [o for o in outs if o.split(".")[0] not in map_stages]
                                   for kind, outs in default["export"].items()}
    assert calibrate.get("input") == default.get("input")


def test_device_option_picks_one_imu(tmp_path, toy_registry, toy_pipeline, monkeypatch):
    mcap_writer = pytest.importorskip("imupipe.writers.mcap")
    import pipeline_real_readers

    from imupipe.components import Recording

    one = ArrowSessionReader().read(write_session(tmp_path / "a.arrowsession", seed=1, bias=0.1))
    two = ArrowSessionReader().read(write_session(tmp_path / "b.arrowsession", seed=2, bias=0.3))
    mcap = tmp_path / "pair.mcap"
    mcap_writer.write_mcap(mcap, Recording("two", {"left": one.device(), "right": two.device()}))
    registry, _ = toy_registry(pipeline_real_readers)
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    out = tmp_path / "out"
    args = ["run", str(mcap), "--pipeline", str(toy_pipeline), "--out", str(out), "--quiet"]
    assert cli.main([*args, "--device", "right"]) == 0
    doc = json.loads((out / "pair" / "calibration.json").read_text())
    np.testing.assert_allclose(doc["gyro"]["b0"], 0.3, atol=0.01)  # the right IMU's bias
    assert cli.main([*args, "--device", "middle"]) == 2
    # a failed run keeps the previous result (issue 12); run.json says the last run failed
    assert json.loads((out / "pair" / "calibration.json").read_text()) == doc
    assert "no device 'middle'" in json.loads((out / "pair" / "run.json").read_text())["error"]
    run_sessions([mcap], toy_pipeline, out, quiet=True, registry=registry,
                 overrides=['input.device="left"'])
    doc = json.loads((out / "pair" / "calibration.json").read_text())
    np.testing.assert_allclose(doc["gyro"]["b0"], 0.1, atol=0.01)


def test_diagnose_takes_set_validated_before_any_data(tmp_path, capsys):
    args = ["diagnose", str(tmp_path / "never-read.mcap"), "--out", str(tmp_path / "o"), "--quiet"]
    assert cli.main([*args, "--set", "map.nope=1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--set map.nope=1: stage 'map' (diagnose) has no parameter" in err

"""``imupipe run``: calibration.json per session, skipped streams, failures leave nothing behind."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from pipeline_toys import TOY_PIPELINE, write_csv, write_manifest, write_session

from imupipe import __version__, cli
from imupipe.components import Stage
from imupipe.errors import ImupipeError, ReaderError, SchemaError
from imupipe.hookspecs import hookimpl
from imupipe.io import read_arrow
from imupipe.models import Calibration
from imupipe.pipeline import api
from imupipe.pipeline.api import run_sessions, session_ids
from imupipe.pipeline.cache import read_manifest

# toy truth: bias 0.1 (mag 1e-7 T) on every axis, noise 0.01 over 200 samples
BIAS_TOL = 0.01 * 4 / np.sqrt(200)


def test_run_writes_calibration_json_of_the_contract(tmp_path, toy_registry, toy_pipeline, session):
    registry, _ = toy_registry()
    out = tmp_path / "out"
    written = run_sessions([session], toy_pipeline, out, quiet=True, registry=registry)
    path = out / "s1" / "calibration.json"
    assert written == [path]
    doc = json.loads(path.read_text())
    assert doc["session"] == str(session) and doc["pipeline"] == "toy"
    assert doc["imupipe_version"] == __version__ and doc["temperature_reference_C"] == 25.0
    # the toy bias stage removes gravity from accel only: mag keeps the toy field
    field = np.array([2e-5, 0.0, 4e-5])
    for sensor, unit, scale, offset in (
        ("accel", "m/s^2", 1.0, 0.0),
        ("gyro", "rad/s", 1.0, 0.0),
        ("mag", "T", 1e-6, field),
    ):
        triad = doc[sensor]
        assert triad["units"] == unit
        assert np.array(triad["M"]).shape == (3, 3) and len(triad["k"]) == 3
        np.testing.assert_allclose(triad["b0"], offset + 0.1 * scale, rtol=0, atol=BIAS_TOL * scale)
    assert doc["accel"]["had_temperature"] is True  # the optional input was wired
    assert "skipped_stages" not in doc
    assert set(Calibration.from_dict(doc).triads) == {"accel", "gyro", "mag"}


def test_missing_stream_skips_stage_and_downstream_and_exports_the_rest(
    tmp_path, toy_registry, caplog
):
    registry, counter = toy_registry()
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(TOY_PIPELINE)
    session = write_session(tmp_path / "nomag.arrowsession", streams=("accel", "gyro"))
    with caplog.at_level("INFO", logger="imupipe.pipeline"):
        run_sessions([session], pipeline, tmp_path / "out", quiet=True, registry=registry)
    doc = json.loads((tmp_path / "out" / "nomag" / "calibration.json").read_text())
    assert "mag" not in doc and {"accel", "gyro"} <= set(doc)
    assert doc["skipped_stages"] == {"mag": "the session has no 'mag' stream"}
    assert doc["accel"]["had_temperature"] is False  # optional input left unwired
    assert "mag" not in counter.ran
    assert "skipping stage 'mag'" in caplog.text


def test_skipped_upstream_skips_downstream(tmp_path, toy_registry):
    registry, _ = toy_registry()
    text = TOY_PIPELINE + (
        '\n[stages.wrapped]\nuses = "toy_bias_accel"\ninputs = { samples = "scaled2.samples" }\n'
        '\n[stages.scaled2]\nuses = "toy_scale"\ninputs = { samples = "scaled.samples" }\n'
    )
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(text)
    session = write_session(tmp_path / "noaccel.arrowsession", streams=("gyro", "mag"))
    run_sessions([session], pipeline, tmp_path / "out", quiet=True, registry=registry)
    manifest = json.loads((tmp_path / "out" / "noaccel" / "run.json").read_text())
    status = {k: v["status"] for k, v in manifest["stages"].items()}
    assert status == {
        "scaled": "skipped",
        "scaled2": "skipped",
        "accel": "skipped",
        "wrapped": "skipped",
        "gyro": "ran",
        "mag": "ran",
    }
    assert "upstream stage 'scaled' was skipped" in manifest["stages"]["scaled2"]["reason"]


class FigureReport:
    """A report exporter as the built-in one writes: report.md and figures/."""

    name = "report"
    writes = ("report.md", "figures")

    def export(self, results, context, out_dir):
        (Path(out_dir) / "figures").mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "figures" / "fit.png").write_bytes(b"png")
        (Path(out_dir) / "report.md").write_text("# report\n")
        return [Path(out_dir) / "report.md"]

    @hookimpl
    def imupipe_register_exporters(self, register):
        register(self)


def test_failing_session_keeps_the_previous_result_and_others_still_run(
    tmp_path, toy_registry, toy_pipeline, session
):
    registry, _ = toy_registry(FigureReport())
    toy_pipeline.write_text(TOY_PIPELINE + 'reports = ["gyro.calibration"]\n')
    out = tmp_path / "out"
    bad = tmp_path / "data" / "bad.arrowsession"
    bad.write_bytes(b"not arrow at all")
    (out / "bad" / "figures").mkdir(parents=True)
    (out / "bad" / "calibration.json").write_text("{}")  # results of an earlier run
    (out / "bad" / "report.md").write_text("# old report")
    (out / "bad" / "figures" / "old.png").write_bytes(b"png")
    (out / "bad" / "notes.txt").write_text("the user's own file")
    with pytest.raises(
        ReaderError,
        match=r"bad.arrowsession: not an Arrow IPC session .*\(1 of 2 sessions failed\)",
    ):
        run_sessions([bad, session], toy_pipeline, out, quiet=True, registry=registry)
    # a failed run removes only what it wrote itself: the earlier result stays as it was
    assert (out / "bad" / "calibration.json").read_text() == "{}"
    assert (out / "bad" / "report.md").read_text() == "# old report"
    assert (out / "bad" / "figures" / "old.png").is_file()
    assert (out / "bad" / "notes.txt").is_file()
    assert read_manifest(out / "bad" / "run.json")["error"]  # status tells the run failed
    assert not [p for p in (out / "bad").iterdir() if p.name.startswith(".")]
    assert (out / "s1" / "calibration.json").is_file()
    assert (out / "s1" / "figures" / "fit.png").is_file()
    assert not list(out.rglob("*.part"))


def test_stage_breaking_its_contract_is_a_schema_error(tmp_path, toy_registry, session):
    registry, _ = toy_registry()
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(
        'name = "broken"\n[stages.b]\nuses = "toy_broken"\ninputs = { samples = "session.accel" }\n'
    )
    with pytest.raises(
        SchemaError, match=r"stage 'b' \(toy_broken\): returned outputs \['wrong'\]"
    ):
        run_sessions([session], pipeline, tmp_path / "out", quiet=True, registry=registry)
    manifest = json.loads((tmp_path / "out" / "s1" / "run.json").read_text())
    assert "SchemaError" in manifest["error"]


def test_report_exporter_is_called_when_registered(tmp_path, toy_registry, session):
    class Report:
        name = "report"

        def __init__(self):
            self.calls = []

        def export(self, results, context, out_dir):
            self.calls.append((dict(results), dict(context), Path(out_dir)))
            return []

    class ReportPlugin:
        def __init__(self):
            self.exporter = Report()

        @hookimpl
        def imupipe_register_exporters(self, register):
            register(self.exporter)

    text = TOY_PIPELINE + 'reports = ["scaled.samples", "gyro.calibration"]\n'
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(text)
    plugin = ReportPlugin()
    registry, _ = toy_registry(plugin)
    run_sessions([session], pipeline, tmp_path / "out", quiet=True, registry=registry)
    ((results, context, out_dir),) = plugin.exporter.calls
    assert list(results) == ["scaled.samples", "gyro.calibration"]
    assert results["scaled.samples"].num_rows == 200
    # exporters write into a staging folder that is moved into place when all have succeeded
    assert context["pipeline"] == "toy" and out_dir.parent == tmp_path / "out" / "s1"
    assert out_dir.name.startswith(".part-") and not out_dir.exists()

    registry, _ = toy_registry()  # no report exporter: reports are skipped, the run succeeds
    run_sessions([session], pipeline, tmp_path / "out2", quiet=True, registry=registry)
    assert (tmp_path / "out2" / "s1" / "calibration.json").is_file()


def test_session_ids_are_stems_made_unique():
    ids = session_ids(
        [Path("a/run.mcap"), Path("b/run.mcap"), Path("x/lab1/session.toml"), Path("c.csv")]
    )
    assert ids[0].startswith("run-") and ids[1].startswith("run-") and ids[0] != ids[1]
    assert ids[2:] == ["lab1", "c"]


def test_cli_run_quiet(tmp_path, toy_registry, toy_pipeline, session, monkeypatch, capsys):
    registry, counter = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    out = tmp_path / "out"
    assert (
        cli.main(
            ["run", str(session), "--pipeline", str(toy_pipeline), "--out", str(out), "--quiet"]
        )
        == 0
    )
    captured = capsys.readouterr()
    assert captured.err == ""
    assert (out / "s1" / "calibration.json").is_file()
    assert len(counter.ran) == 4


def test_cli_run_bad_session_exits_2(tmp_path, toy_registry, toy_pipeline, monkeypatch, capsys):
    registry, _ = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    missing = tmp_path / "nope.arrowsession"
    assert (
        cli.main(
            [
                "run",
                str(missing),
                "--pipeline",
                str(toy_pipeline),
                "--out",
                str(tmp_path / "o"),
                "--quiet",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nope.arrowsession: no such file" in err
    args = ["run", str(tmp_path), "--pipeline", str(toy_pipeline), "--out", str(tmp_path / "o")]
    assert cli.main(args) == 2
    assert "is a directory; give a recording file or a session.toml" in capsys.readouterr().err


def test_recording_is_not_read_when_everything_is_cached(
    tmp_path, toy_registry, toy_pipeline, session, monkeypatch
):
    registry, _ = toy_registry()
    run_sessions([session], toy_pipeline, tmp_path / "out", quiet=True, registry=registry)

    def refuse(*a, **k):
        raise AssertionError("the recording was read although every stage is cached")

    from imupipe.pipeline import runner

    monkeypatch.setattr(runner, "read_recording", refuse)
    registry, counter = toy_registry()
    run_sessions([session], toy_pipeline, tmp_path / "out", quiet=True, registry=registry)
    assert counter.ran == []
    # the exported table is the cached one
    rec = json.loads((tmp_path / "out" / "s1" / "run.json").read_text())["stages"]["gyro"]
    key = rec["key"]
    assert (
        read_arrow(tmp_path / "out" / ".cache" / key[:2] / key / "calibration.arrow").num_rows == 1
    )


def test_run_with_no_exportable_calibration_fails(tmp_path, toy_registry):
    registry, _ = toy_registry()
    pipeline = tmp_path / "p.toml"
    # only the mag stage is exported; a session without mag skips it (a recording without
    # any IMU stream is rejected by the reader check already)
    pipeline.write_text(
        TOY_PIPELINE.replace(
            '["accel.calibration", "gyro.calibration", "mag.calibration"]', '["mag.calibration"]'
        )
    )
    session = write_session(tmp_path / "tonly.arrowsession", streams=("gyro", "temperature"))
    with pytest.raises(ImupipeError, match="no calibration table to export"):
        run_sessions([session], pipeline, tmp_path / "out", quiet=True, registry=registry)
    assert not (tmp_path / "out" / "tonly" / "calibration.json").exists()


def test_report_needing_a_missing_extra_warns_and_keeps_the_calibration(
    tmp_path, toy_registry, session
):
    from imupipe.errors import MissingExtraError

    class NeedsExtra:
        name = "report"

        def export(self, results, context, out_dir):
            raise MissingExtraError("matplotlib", "report")

    class Plugin:
        @hookimpl
        def imupipe_register_exporters(self, register):
            register(NeedsExtra())

    pipeline = tmp_path / "p.toml"
    pipeline.write_text(TOY_PIPELINE + 'reports = ["gyro.calibration"]\n')
    registry, _ = toy_registry(Plugin())
    with pytest.warns(UserWarning, match=r"no report written: .*imupipe\[report\]"):
        run_sessions([session], pipeline, tmp_path / "out", quiet=True, registry=registry)
    assert (tmp_path / "out" / "s1" / "calibration.json").is_file()


class WarningStage:
    """A stage that warns about its data, as the thermal stage does when it gives up on k."""

    @staticmethod
    def _func(inputs, params, solver):
        warnings.warn("too little temperature range; continuing with k = 0", stacklevel=2)
        warnings.warn("too little temperature range; continuing with k = 0", stacklevel=2)
        return {"samples": inputs["samples"]}

    @hookimpl
    def imupipe_register_stages(self, register):
        register(Stage("toy_warn", "1", self._func, inputs={"samples": "accel"},
                       outputs={"samples": "accel"}))


def test_stage_warnings_are_logged_recorded_and_replayed_from_the_cache(
    tmp_path, toy_registry, session, caplog
):
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(TOY_PIPELINE.replace('inputs = { samples = "session.accel" }',
                                             'inputs = { samples = "warned.samples" }')
                        + '\n[stages.warned]\nuses = "toy_warn"\n'
                          'inputs = { samples = "session.accel" }\n')
    message = "warned: too little temperature range; continuing with k = 0"
    for status in ("ran", "cached"):
        registry, _ = toy_registry(WarningStage())
        caplog.clear()
        with warnings.catch_warnings(), caplog.at_level("WARNING", logger="imupipe.pipeline"):
            warnings.simplefilter("error")  # nothing escapes as a Python warning
            run_sessions([session], pipeline, tmp_path / "out", quiet=True, registry=registry)
        assert [r.getMessage() for r in caplog.records] == [message]  # once, on the cache hit too
        record = json.loads((tmp_path / "out" / "s1" / "run.json").read_text())["stages"]["warned"]
        assert record["status"] == status
        assert record["warnings"] == [message.removeprefix("warned: ")]


def test_counts_session_says_the_raw_units_in_calibration_json(tmp_path, toy_registry):
    import imupipe.readers

    rng = np.random.default_rng(3)
    write_csv(tmp_path / "acc.csv", 32768 + 100 * rng.standard_normal((200, 3)))
    write_csv(tmp_path / "gyro.csv", np.full((200, 3), 0.001))
    manifest = write_manifest(
        tmp_path / "session.toml",
        "counts",
        {"stream": "accel", "file": "acc.csv", "unit": "counts"},
        {"stream": "gyro", "file": "gyro.csv", "unit": "rad/s"},
    )
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(TOY_PIPELINE.replace('gravity = "z"', 'gravity = "none"'))
    for _ in range(2):  # the second run reads nothing: the units come from run.json
        registry, counter = toy_registry(imupipe.readers)
        run_sessions([manifest], pipeline, tmp_path / "out", quiet=True, registry=registry)
        doc = json.loads((tmp_path / "out" / tmp_path.name / "calibration.json").read_text())
        assert doc["accel"]["units"] == "m/s^2" and doc["accel"]["raw_units"] == "counts"
        assert doc["accel"]["raw_units_note"] == (
            "b0 in counts, k in counts/degC; M maps counts to m/s^2"
        )
        assert doc["accel"]["b0"][0] > 30000  # the toy bias is the mean: in counts
        assert doc["gyro"]["raw_units"] == "rad/s" and "raw_units_note" not in doc["gyro"]
    assert counter.ran == []

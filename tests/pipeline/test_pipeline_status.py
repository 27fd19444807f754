"""``imupipe status``: what is stale and why, decided before anything runs."""

from __future__ import annotations

from pipeline_toys import TOY_PIPELINE, MeanParams, status_lines, write_session

from imupipe import cli
from imupipe.hookspecs import hookimpl
from imupipe.pipeline import api
from imupipe.pipeline.api import run_sessions, status

_lines = status_lines


def test_status_before_and_after_a_run(tmp_path, toy_registry, toy_pipeline, session):
    registry, counter = toy_registry()
    out = tmp_path / "out"
    before = _lines(status([session], toy_pipeline, out, registry=registry))
    assert before == {k: "stale never run" for k in ("scaled", "accel", "gyro", "mag")}
    assert counter.ran == []  # status runs nothing

    run_sessions([session], toy_pipeline, out, quiet=True, registry=registry)
    after = status([session], toy_pipeline, out, registry=registry)
    assert after.splitlines()[0].endswith("0 stale, 4 fresh")
    assert set(_lines(after).values()) == {"fresh"}


def test_status_says_why(tmp_path, toy_registry, toy_pipeline, session):
    out = tmp_path / "out"
    run_sessions([session], toy_pipeline, out, quiet=True, registry=toy_registry()[0])

    registry, _ = toy_registry(bias_version="2")
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["gyro"] == "stale version changed 1 -> 2"
    assert lines["scaled"] == "fresh"

    toy_pipeline.write_text(
        TOY_PIPELINE.replace("factor = 1.0", "factor = 2.5").replace("scale = 1.0", "scale = 2.0")
    )
    registry, counter = toy_registry()
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["scaled"] == "stale param factor changed 1.0 -> 2.5"
    assert lines["accel"].startswith("stale upstream 'scaled' is stale")
    assert lines["mag"] == "stale solver param scale changed 1.0 -> 2.0"
    assert lines["gyro"] == "fresh"

    toy_pipeline.write_text(TOY_PIPELINE)
    write_session(session, seed=5)
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["gyro"] == "stale input 'samples' changed (the session file changed)"
    assert counter.ran == []


def test_status_with_no_session_uses_those_run_in_out(
    tmp_path, toy_registry, toy_pipeline, session
):
    registry, _ = toy_registry()
    out = tmp_path / "out"
    assert "no sessions have been run here" in status([], toy_pipeline, out, registry=registry)
    nomag = write_session(tmp_path / "nomag.arrowsession", streams=("accel", "gyro"))
    run_sessions([session, nomag], toy_pipeline, out, quiet=True, registry=registry)
    text = status([], toy_pipeline, out, registry=registry)
    heads = [line for line in text.splitlines() if not line.startswith(" ")]
    assert len(heads) == 2 and any("s1.arrowsession" in h for h in heads)
    assert "skipped mag     the session has no 'mag' stream" in text
    assert "stale" not in text.replace("0 stale", "")


def test_cli_status(tmp_path, toy_registry, toy_pipeline, session, monkeypatch, capsys):
    registry, _ = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    out = tmp_path / "out"
    assert (
        cli.main(["status", str(session), "--pipeline", str(toy_pipeline), "--out", str(out)]) == 0
    )
    assert "stale   scaled" in capsys.readouterr().out


def test_status_without_pipeline_uses_the_one_recorded_in_run_json(
    tmp_path, toy_registry, toy_pipeline, session
):
    registry, _ = toy_registry()
    out = tmp_path / "out"
    run_sessions([session], toy_pipeline, out, quiet=True, registry=registry)
    text = status([session], None, out, registry=registry)  # the default pipeline is not toy
    assert f"from run.json: {toy_pipeline.resolve()}" in text.splitlines()[0]
    assert set(_lines(text).values()) == {"fresh"}
    assert set(_lines(status([], None, out, registry=registry)).values()) == {"fresh"}


class OtherToySolver:
    name = "toy_mean_other"
    kind = "toy"
    version = "1"
    params = MeanParams

    def solve(self, observations, params):
        return observations.mean(axis=0)

    @hookimpl
    def imupipe_register_solvers(self, register):
        register(self)


def test_a_solver_change_is_said_once(tmp_path, toy_registry, toy_pipeline, session):
    out = tmp_path / "out"
    run_sessions([session], toy_pipeline, out, quiet=True, registry=toy_registry()[0])
    toy_pipeline.write_text(
        TOY_PIPELINE.replace("solver_params = { scale = 1.0 }", 'solver = "toy_mean_other"')
    )
    registry, _ = toy_registry(OtherToySolver())
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["mag"] == "stale solver changed toy_mean -> toy_mean_other"


def test_status_says_why_the_last_run_failed(tmp_path, toy_registry, toy_pipeline):
    import pytest

    from imupipe.errors import ReaderError

    registry, _ = toy_registry()
    bad = tmp_path / "bad.arrowsession"
    bad.write_bytes(b"not arrow at all")
    out = tmp_path / "out"
    with pytest.raises(ReaderError):
        run_sessions([bad], toy_pipeline, out, quiet=True, registry=registry)
    text = status([], None, out, registry=registry)
    assert "last run failed: ReaderError:" in text and "not an Arrow IPC session" in text

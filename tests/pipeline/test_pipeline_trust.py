"""Issue 12: nothing written or deleted outside --out, a cache that checks itself, no lost results."""

from __future__ import annotations

import os

import pytest
from pipeline_toys import ArrowSessionReader, write_session

from imupipe import cli
from imupipe.components import Recording
from imupipe.errors import ImupipeError
from imupipe.hookspecs import hookimpl
from imupipe.ingest import write_recording
from imupipe.paths import safe_name, under, unique_names
from imupipe.pipeline import api
from imupipe.pipeline.api import run_sessions, session_ids
from imupipe.pipeline.cache import read_manifest


def _files(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def test_safe_names_are_plain_and_unique():
    for hostile in ("..", ".", "", "a/../..", "/", "\x00", ".hidden", "../etc/passwd", "a" * 500):
        name = safe_name(hostile)
        assert name and name not in (".", "..") and "/" not in name and not name.startswith(".")
        assert len(name) <= 120
    names = unique_names(["a/b", "a_b", "A_B", "..", "/imu0/data"])
    assert names["a_b"] == "a_b" and names["/imu0/data"] == "imu0_data"
    assert len({n.lower() for n in names.values()}) == 5


def test_under_refuses_paths_out_of_the_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    assert under(out, "s1", "calibration.json") == out / "s1" / "calibration.json"
    with pytest.raises(ImupipeError, match="outside the output folder"):
        under(out, "..", "report.md")
    (out / "link").symlink_to(tmp_path)
    with pytest.raises(ImupipeError, match="outside the output folder"):
        under(out, "link", "calibration.json")
    (out / "loop").symlink_to(out / "loop")
    with pytest.raises(ImupipeError, match="loop|outside"):
        under(out, "loop", "x")


def test_session_stem_dotdot_stays_inside_out(tmp_path, toy_registry, toy_pipeline):
    (tmp_path / "data").mkdir()
    hostile = write_session(tmp_path / "data" / "...arrowsession", seed=1)
    assert hostile.stem == ".."
    out = tmp_path / "work" / "out"
    (tmp_path / "work" / "report.md").parent.mkdir(parents=True)
    (tmp_path / "work" / "report.md").write_text("mine")
    before = _files(tmp_path / "work")
    (path,) = run_sessions([hostile], toy_pipeline, out, quiet=True, registry=toy_registry()[0])
    assert path.is_file() and path.resolve().is_relative_to(out.resolve())
    after = [f for f in _files(tmp_path / "work") if not f.startswith("out")]
    assert after == [f for f in before if not f.startswith("out")]
    assert (tmp_path / "work" / "report.md").read_text() == "mine"
    (sid,) = session_ids([hostile])
    assert sid not in ("..", ".") and "/" not in sid


def test_device_names_dotdot_and_collisions_stay_apart(tmp_path):
    streams = ArrowSessionReader().read(write_session(tmp_path / "s.arrowsession", seed=1)).device()
    recording = Recording("x", {"..": streams, "a/b": streams, "a_b": streams, "/../imu": streams})
    out = tmp_path / "deep" / "out"
    written = write_recording(recording, out)
    assert all(p.resolve().is_relative_to(out.resolve()) for p in written)
    assert len({p.parent for p in written}) == 4  # one folder per device, none shared
    assert not (tmp_path / "deep" / "accel.arrow").exists()


class FailingReport:
    """A report exporter that fails after calibration.json was staged."""

    name = "report"
    writes = ("report.md",)

    def export(self, results, context, out_dir):
        (out_dir / "report.md").write_text("half")
        raise ImupipeError("report: disk full")

    @hookimpl
    def imupipe_register_exporters(self, register):
        register(self)


def test_failed_run_keeps_the_previous_or_concurrent_result(tmp_path, toy_registry, toy_pipeline,
                                                           session):
    out = tmp_path / "out"
    (good,) = run_sessions([session], toy_pipeline, out, quiet=True, registry=toy_registry()[0])
    text = good.read_text()
    toy_pipeline.write_text(toy_pipeline.read_text() + 'reports = ["gyro.calibration"]\n')
    with pytest.raises(ImupipeError, match="disk full"):
        run_sessions([session], toy_pipeline, out, quiet=True,
                     registry=toy_registry(FailingReport())[0])
    assert good.read_text() == text  # neither deleted nor replaced by the failed run's
    assert not (out / "s1" / "report.md").exists()  # nothing half-written left
    assert not [p for p in (out / "s1").iterdir() if p.name.startswith(".part")]  # no staging left
    assert read_manifest(out / "s1" / "run.json")["error"]


def test_stale_part_files_of_a_killed_run_are_removed(tmp_path, toy_registry, toy_pipeline,
                                                      session):
    out = tmp_path / "out"
    run_sessions([session], toy_pipeline, out, quiet=True, registry=toy_registry()[0])
    dead = 2**22 + 12345  # above the default pid_max: no such process
    staged = out / "s1" / f".part-{dead}-abcd1234"
    staged.mkdir()
    (staged / "calibration.json").write_text("{}")
    entry = next((out / ".cache").glob("*/*"))
    part = entry / f".calibration.arrow.{dead}.x1y2.part"
    part.write_bytes(b"half")
    alive = out / "s1" / f".part-{os.getpid()}-live0000"  # a concurrent run's: left alone
    alive.mkdir()
    run_sessions([session], toy_pipeline, out, quiet=True, registry=toy_registry()[0])
    assert not staged.exists() and not part.exists() and alive.exists()


@pytest.mark.parametrize("kind", ["file", "below_file"])
def test_out_that_is_a_file_is_one_line(tmp_path, toy_registry, toy_pipeline, session, monkeypatch,
                                        capsys, kind):
    registry, _ = toy_registry()
    monkeypatch.setattr(api, "make_registry", lambda *a, **k: registry)
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    out = blocker if kind == "file" else blocker / "sub"
    code = cli.main(["run", str(session), "--pipeline", str(toy_pipeline), "--out", str(out),
                     "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--out" in err and "Traceback" not in err


def test_batch_skips_fifos_and_link_loops_in_a_folder(tmp_path, toy_pipeline, caplog):
    from pipeline_toys import TOY_SPEC

    from imupipe.pipeline.api import batch

    data = tmp_path / "data"
    data.mkdir()
    write_session(data / "good.arrowsession", seed=1)
    os.mkfifo(data / "pipe.arrowsession")
    (data / "loop.arrowsession").symlink_to(data / "loop.arrowsession")
    failures = batch([str(data)], toy_pipeline, tmp_path / "out", "local", 1, quiet=True,
                     plugins=TOY_SPEC)
    assert failures == []
    assert (tmp_path / "out" / "good" / "calibration.json").is_file()
    assert "pipe.arrowsession: skipped: not a regular file" in caplog.text


class _RaisingObserver:
    @hookimpl
    def imupipe_after_stage(self, stage, key, cached, seconds):
        raise RuntimeError("observer bug")


def test_a_raising_lifecycle_hook_does_not_stop_the_run(tmp_path, toy_registry, toy_pipeline,
                                                       session, caplog):
    registry, counter = toy_registry(_RaisingObserver())
    (path,) = run_sessions([session], toy_pipeline, tmp_path / "out", quiet=True,
                           registry=registry)
    assert path.is_file()
    assert sorted(counter.ran) == ["accel", "gyro", "mag", "scaled"]  # the others still observe
    assert caplog.text.count("imupipe_after_stage raised RuntimeError: observer bug") == 1
    assert any("observer bug" in why for _, _, why in registry.broken.values())

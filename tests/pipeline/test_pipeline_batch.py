"""``imupipe batch``: input expansion, local process pool and a real Dask cluster, failures."""

from __future__ import annotations

import json

import pytest
from pipeline_toys import TOY_SPEC, write_session

from imupipe import cli
from imupipe.errors import ImupipeError
from imupipe.pipeline import api
from imupipe.pipeline.api import batch, expand_inputs


@pytest.fixture
def sessions(tmp_path):
    data = tmp_path / "data"
    (data / "lab" / "manifest_session").mkdir(parents=True)
    (data / ".hidden").mkdir()
    good = [write_session(data / f"good{i}.arrowsession", seed=i) for i in range(3)]
    bad = data / "bad.arrowsession"
    bad.write_bytes(b"garbage, not Arrow")
    write_session(data / ".hidden" / "ignored.arrowsession")
    (data / "notes.txt").write_text("not a session")
    return data, good, bad


def test_expand_inputs_dirs_globs_manifests(tmp_path, sessions, toy_registry):
    data, good, bad = sessions
    registry, _ = toy_registry()
    manifest = data / "lab" / "manifest_session" / "session.toml"
    manifest.write_text('files = ["a.arrowsession"]\n')
    write_session(manifest.parent / "a.arrowsession")  # a manifest's data file is not a session
    out = data / "out"
    write_session(out / "x.arrowsession")  # nothing is taken from the output directory
    found = expand_inputs([str(data)], registry, out)
    assert found == sorted([bad.resolve(), *(g.resolve() for g in good), manifest.resolve()])
    assert expand_inputs([str(data / "good*.arrowsession")], registry) == [
        g.resolve() for g in good
    ]
    with pytest.raises(ImupipeError, match="no such file, directory or matching glob"):
        expand_inputs([str(data / "nothing*.mcap")], registry)


@pytest.mark.parametrize("jobs", [1, 2])
def test_local_batch_reports_failures_and_keeps_going(
    tmp_path, sessions, toy_pipeline, capsys, jobs
):
    data, good, bad = sessions
    out = tmp_path / "out"
    failures = batch(
        [str(data / "*.arrowsession")],
        toy_pipeline,
        out,
        "local",
        jobs,
        quiet=True,
        plugins=TOY_SPEC,
    )
    assert [f.session for f in failures] == [str(bad.resolve())]
    assert "not an Arrow IPC session" in failures[0].detail
    for g in good:
        doc = json.loads((out / g.stem / "calibration.json").read_text())
        assert doc["pipeline"] == "toy" and set(doc) >= {"accel", "gyro", "mag"}
    assert not (out / "bad" / "calibration.json").exists()
    table = capsys.readouterr().out
    assert "3 ok, 1 failed" in table
    bad_line = next(line for line in table.splitlines() if "bad.arrowsession" in line)
    assert "failed" in bad_line and "not an Arrow IPC session" in bad_line


def test_cli_batch_exits_2_when_a_session_fails(
    tmp_path, sessions, toy_pipeline, monkeypatch, capsys
):
    data, _, bad = sessions
    monkeypatch.setattr(api, "DEFAULT_SPEC", TOY_SPEC)
    out = tmp_path / "out"
    options = ["--pipeline", str(toy_pipeline), "--out", str(out), "--jobs", "1", "--quiet"]
    assert cli.main(["batch", str(data / "good0.arrowsession"), *options]) == 0
    assert cli.main(["batch", str(data / "good0.arrowsession"), str(bad), *options]) == 2
    assert "1 ok, 1 failed" in capsys.readouterr().out


def test_unknown_executor_names_the_known_ones(tmp_path, sessions, toy_pipeline):
    data, _, _ = sessions
    with pytest.raises(ImupipeError, match="no executor named 'ray'; known executors: dask, local"):
        batch([str(data)], toy_pipeline, tmp_path / "out", "ray", 1, quiet=True, plugins=TOY_SPEC)


def test_dask_batch_on_a_real_local_cluster(tmp_path, sessions, toy_pipeline, monkeypatch, capsys):
    pytest.importorskip("distributed")
    monkeypatch.delenv("IMUPIPE_DASK_SCHEDULER", raising=False)
    data, good, bad = sessions
    out = tmp_path / "out"
    # jobs=2: a LocalCluster of 2 worker processes, 1 thread each
    failures = batch(
        [str(data / "*.arrowsession")], toy_pipeline, out, "dask", 2, quiet=True, plugins=TOY_SPEC
    )
    assert [f.session for f in failures] == [str(bad.resolve())]
    assert "not an Arrow IPC session" in failures[0].detail
    assert all((out / g.stem / "calibration.json").is_file() for g in good)
    assert "3 ok, 1 failed" in capsys.readouterr().out


def test_dask_batch_uses_the_scheduler_named_in_the_environment(
    tmp_path, sessions, toy_pipeline, monkeypatch
):
    distributed = pytest.importorskip("distributed")
    _, good, _ = sessions
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        monkeypatch.setenv("IMUPIPE_DASK_SCHEDULER", cluster.scheduler_address)
        failures = batch(
            [str(g) for g in good[:2]],
            toy_pipeline,
            tmp_path / "out",
            "dask",
            2,
            quiet=True,
            plugins=TOY_SPEC,
        )
        assert failures == []
        assert "run_job" in cluster.scheduler.task_prefixes  # the jobs went to this cluster
    assert all((tmp_path / "out" / g.stem / "calibration.json").is_file() for g in good[:2])


def test_expand_inputs_skips_files_no_reader_claims(tmp_path, toy_registry, caplog):
    from imupipe.hookspecs import hookimpl

    class TomlSessions:
        name = "toml_sessions"
        suffixes = (".toml",)

        def sniff(self, path, head):
            return head.startswith(b"[session]")

        def read(self, path):
            raise NotImplementedError

    class Plugin:
        @hookimpl
        def imupipe_register_readers(self, register):
            register(TomlSessions())

    registry, _ = toy_registry(Plugin())
    (tmp_path / "pipeline.toml").write_text('name = "not a session"\n')
    (tmp_path / "lab.toml").write_text("[session]\n")
    good = write_session(tmp_path / "a.arrowsession")
    with caplog.at_level("WARNING", logger="imupipe.pipeline"):
        found = expand_inputs([str(tmp_path)], registry)
    assert found == [good.resolve(), (tmp_path / "lab.toml").resolve()]
    assert "pipeline.toml: skipped: no reader accepts it (toml_sessions)" in caplog.text


def test_local_batch_survives_a_worker_that_dies(tmp_path, toy_pipeline):
    from pipeline_toys import CRASH_ROWS

    data = tmp_path / "data"
    data.mkdir()
    good = [write_session(data / f"g{i}.arrowsession", seed=i) for i in range(2)]
    crash = write_session(data / "crash.arrowsession", n=CRASH_ROWS)
    text = toy_pipeline.read_text().replace(
        "[export]",
        '[stages.c]\nuses = "toy_crash"\ninputs = { samples = "session.accel" }\n\n[export]',
    )
    toy_pipeline.write_text(text)
    failures = batch(
        [str(data)], toy_pipeline, tmp_path / "out", "local", 2, quiet=True, plugins=TOY_SPEC
    )
    assert [f.session for f in failures] == [str(crash.resolve())]
    assert failures[0].detail.startswith("worker died")
    assert all((tmp_path / "out" / g.stem / "calibration.json").is_file() for g in good)


def test_dask_workers_start_without_malloc_trim_and_quietly(monkeypatch, caplog):
    """Dask's MALLOC_TRIM_THRESHOLD_=65536 slowed the workers 1.4-1.9x; its info lines cluttered."""
    import logging
    import os

    pytest.importorskip("distributed")
    from imupipe.pipeline.executors import SCHEDULER_ENV, DaskExecutor

    monkeypatch.delenv(SCHEDULER_ENV, raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    caplog.set_level(logging.INFO)  # every record is seen...
    caplog.set_level(logging.WARNING, logger="imupipe")  # ...while imupipe is not verbose
    got = DaskExecutor().map(os.getenv, ["MALLOC_TRIM_THRESHOLD_", "PYTHONHASHSEED"], 1)
    assert got[0] is None
    assert got[1] is not None  # the variable lookup did run in a Dask worker
    loud = [r for r in caplog.records if r.name.startswith("distributed") and r.levelno < logging.WARNING]
    assert loud == []


def test_dask_workers_poll_their_loop_system_and_memory_seldom(monkeypatch):
    """Dask's 20 ms loop ticks and 100-500 ms monitors cost a batch about 0.5 s CPU in 20."""
    pytest.importorskip("distributed")
    import dask

    from imupipe.pipeline.executors import SCHEDULER_ENV, DaskExecutor

    monkeypatch.delenv(SCHEDULER_ENV, raising=False)
    keys = ["distributed.admin.tick.interval", "distributed.admin.system-monitor.interval",
            "distributed.worker.memory.monitor-interval", "distributed.worker.profile.enabled"]
    assert DaskExecutor().map(dask.config.get, keys, 1) == ["1s", "10s", "1s", False]
    assert dask.config.get(keys[0]) != "1s"  # the caller's configuration is left as it was

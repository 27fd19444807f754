"""Exported files are cached artefacts: a warm run rewrites nothing, a warm batch dispatches nothing."""

from __future__ import annotations

import json

from pipeline_toys import TOY_SPEC

from imupipe.hookspecs import hookimpl
from imupipe.pipeline import api
from imupipe.pipeline.api import CACHE_DIR, batch, run_sessions
from imupipe.pipeline.export_cache import MARKER


class CountingReport:
    """A ``report`` exporter that counts its calls and writes two files."""

    name = "report"
    version = "1"
    writes = ("report.md", "figures")

    def __init__(self):
        self.calls = 0

    def export(self, results, context, out_dir):
        self.calls += 1
        (out_dir / "figures").mkdir(parents=True, exist_ok=True)
        paths = [out_dir / "report.md", out_dir / "figures" / "a.png"]
        paths[0].write_text(f"# {context['session']}: {sorted(results)}\n")
        paths[1].write_bytes(b"png")
        return paths

    @hookimpl
    def imupipe_register_exporters(self, register):
        register(self)


def _with_reports(toy_pipeline):
    text = toy_pipeline.read_text().replace(
        '[export]\n', '[export]\nreports = ["accel.calibration"]\n')
    toy_pipeline.write_text(text)
    return toy_pipeline


def test_warm_run_rewrites_no_export_and_restores_deleted_ones(
        tmp_path, toy_registry, toy_pipeline, session):
    report = CountingReport()
    registry, _ = toy_registry(report)
    pipeline, out = _with_reports(toy_pipeline), tmp_path / "out"
    run_sessions([session], pipeline, out, quiet=True, registry=registry)
    files = [out / "s1" / n for n in ("calibration.json", "report.md", "figures/a.png")]
    stats = [f.stat().st_mtime_ns for f in files]
    assert report.calls == 1

    run_sessions([session], pipeline, out, quiet=True, registry=registry)
    assert report.calls == 1  # nothing redrawn
    assert [f.stat().st_mtime_ns for f in files] == stats  # nothing rewritten

    files[2].unlink()  # a deleted figure comes back from the cache, the exporter is not called
    (out / "s1" / "figures" / "stale.png").write_bytes(b"old")
    run_sessions([session], pipeline, out, quiet=True, registry=registry)
    assert report.calls == 1
    assert files[2].read_bytes() == b"png"
    assert not (out / "s1" / "figures" / "stale.png").exists()  # exactly the cached set

    # a changed input table: the exporter runs again
    text = pipeline.read_text().replace("factor = 1.0", "factor = 2.0")
    pipeline.write_text(text)
    run_sessions([session], pipeline, out, quiet=True, registry=registry)
    assert report.calls == 2
    marker = json.loads((out / "s1" / MARKER).read_text())
    assert set(marker) == {"calibration_json", "residual_map", "diagnosis", "noise_json", "report"}
    assert marker["residual_map"]["files"] == {}  # no map table in this pipeline: nothing written
    # and back: both versions are in the cache
    pipeline.write_text(text.replace("factor = 2.0", "factor = 1.0"))
    run_sessions([session], pipeline, out, quiet=True, registry=registry)
    assert report.calls == 2
    assert len(list((out / CACHE_DIR / "exports").glob("*/*/files.json"))) == 10  # 2 x (json, map, diagnosis, noise, report)


def test_warm_batch_sends_no_job_to_a_worker(tmp_path, toy_pipeline, session, monkeypatch):
    out = tmp_path / "out"
    assert batch([str(session)], toy_pipeline, out, "local", 1, quiet=True, plugins=TOY_SPEC) == []
    before = (out / "s1" / "run.json").stat().st_mtime_ns
    dispatched = []
    real = api.run_job
    monkeypatch.setattr(api, "run_job", lambda job: dispatched.append(job) or real(job))
    assert batch([str(session)], toy_pipeline, out, "local", 1, quiet=True, plugins=TOY_SPEC) == []
    assert dispatched == []
    assert (out / "s1" / "run.json").stat().st_mtime_ns == before
    # a changed parameter: the session is dispatched again
    toy_pipeline.write_text(toy_pipeline.read_text().replace("factor = 1.0", "factor = 3.0"))
    assert batch([str(session)], toy_pipeline, out, "local", 1, quiet=True, plugins=TOY_SPEC) == []
    assert len(dispatched) == 1
    # a deleted calibration.json: dispatched, and restored
    (out / "s1" / "calibration.json").unlink()
    assert batch([str(session)], toy_pipeline, out, "local", 1, quiet=True, plugins=TOY_SPEC) == []
    assert len(dispatched) == 2 and (out / "s1" / "calibration.json").is_file()

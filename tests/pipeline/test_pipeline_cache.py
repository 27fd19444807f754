"""The content-addressed cache: what reruns after a change, early cutoff, provenance."""

from __future__ import annotations

import json
import shutil

from pipeline_toys import TOY_PIPELINE, write_session

from imupipe.io import table_digest
from imupipe.pipeline.api import CACHE_DIR, run_sessions
from imupipe.pipeline.cache import Cache, provenance, read_manifest


def _run(registry, session, pipeline, out):
    return run_sessions([session], pipeline, out, quiet=True, registry=registry)


def test_second_run_of_unchanged_pipeline_executes_nothing(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "gyro", "mag", "scaled"]
    first = (out / "s1" / "calibration.json").read_text()

    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert counter.ran == [] and counter.before == []
    assert sorted(counter.cached) == ["accel", "gyro", "mag", "scaled"]
    assert (out / "s1" / "calibration.json").read_text() == first


def test_version_bump_reruns_exactly_that_stage_and_its_dependents(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    # a new version whose output differs: the stage and everything downstream rerun
    registry, counter = toy_registry(scale_version="2", scale_offset=0.5)
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "scaled"]
    assert sorted(counter.cached) == ["gyro", "mag"]
    b0 = json.loads((out / "s1" / "calibration.json").read_text())["accel"]["b0"]
    assert all(v > 0.5 for v in b0)  # the new behaviour reached the export

    registry, counter = toy_registry(bias_version="7", scale_version="2", scale_offset=0.5)
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "gyro", "mag"]
    assert counter.cached == ["scaled"]


def test_early_cutoff_version_bump_with_identical_output(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    registry, counter = toy_registry(scale_version="2")  # same behaviour, new version
    _run(registry, session, toy_pipeline, out)
    assert counter.ran == ["scaled"]  # reran, produced the same table ...
    assert "accel" in counter.cached  # ... so its dependent is not invalidated


def test_param_change_reruns_stage_and_dependents_and_cutoff_on_noop_param(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)

    toy_pipeline.write_text(TOY_PIPELINE.replace("factor = 1.0", 'factor = 1.0\nlabel = "renamed"'))
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert counter.ran == ["scaled"]  # a param that does not change the output: early cutoff

    toy_pipeline.write_text(TOY_PIPELINE.replace("factor = 1.0", "factor = 2.0"))
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "scaled"]

    toy_pipeline.write_text(TOY_PIPELINE.replace("scale = 1.0", "scale = 3.0"))  # a solver param
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    # scaled is back to factor 1.0, whose run the cache still holds (so is accel's): only mag runs
    assert counter.ran == ["mag"]
    assert sorted(counter.cached) == ["accel", "gyro", "scaled"]


def test_changed_session_file_reruns_its_consumers(tmp_path, toy_registry, toy_pipeline, session):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    write_session(session, seed=99)
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "gyro", "mag", "scaled"]


def test_outputs_carry_provenance_and_round_trip_their_digest(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    manifest = read_manifest(out / "s1" / "run.json")
    rec = manifest["stages"]["scaled"]
    assert rec["status"] == "ran" and rec["parts"]["version"] == "1"
    cache = Cache(out / CACHE_DIR)
    path = out / CACHE_DIR / rec["key"][:2] / rec["key"] / "samples.arrow"
    prov = provenance(path)
    assert prov["stage"] == "scaled" and prov["uses"] == "toy_scale" and prov["key"] == rec["key"]
    assert prov["digest"] == rec["outputs"]["samples"]
    assert set(prov["inputs"]) == {"samples"} and prov["imupipe_version"]
    table = cache.load(rec["key"], "samples")
    assert table_digest(table) == rec["outputs"]["samples"]
    # downstream keys use the upstream output digest
    assert manifest["stages"]["accel"]["parts"]["inputs"]["samples"] == rec["outputs"]["samples"]
    assert not list(out.rglob("*.part"))


def test_incomplete_cache_entry_is_not_a_hit(tmp_path, toy_registry, toy_pipeline, session):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    key = read_manifest(out / "s1" / "run.json")["stages"]["gyro"]["key"]
    (out / CACHE_DIR / key[:2] / key / "calibration.arrow").unlink()
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert counter.ran == ["gyro"]


def test_solver_version_bump_reruns_the_stages_using_it(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    registry, counter = toy_registry(solver_version="2")
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "gyro", "mag"]
    assert counter.cached == ["scaled"]


def test_manifest_session_digest_covers_the_files_it_names(tmp_path):
    from imupipe.pipeline.cache import session_digest
    from imupipe.readers.manifest import ManifestReader

    (tmp_path / "sub").mkdir()
    (tmp_path / "acc.csv").write_text("1,2,3\n")
    (tmp_path / "sub" / "gyro.csv").write_text("4,5,6\n")
    manifest = tmp_path / "session.toml"
    manifest.write_text(
        '[session]\nname = "lab"\n'
        '[[streams]]\nstream = "accel"\nfile = "acc.csv"\nrate_hz = 100\n'
        '[[streams]]\nstream = "gyro"\nfile = "sub/gyro.csv"\nrate_hz = 100\n'
    )
    reader = ManifestReader()
    assert reader.inputs(manifest) == [tmp_path / "acc.csv", tmp_path / "sub" / "gyro.csv"]
    before = session_digest(manifest, reader)
    (tmp_path / "sub" / "gyro.csv").write_text("4,5,7\n")
    assert session_digest(manifest, reader) != before  # a data file changed, the manifest did not


def test_damaged_cache_entry_is_a_miss_with_a_warning(
    tmp_path, toy_registry, toy_pipeline, session, caplog
):
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    first = (out / "s1" / "calibration.json").read_text()
    key = read_manifest(out / "s1" / "run.json")["stages"]["gyro"]["key"]
    path = out / CACHE_DIR / key[:2] / key / "calibration.arrow"
    data = bytearray(path.read_bytes())
    for i in (len(data) // 3, len(data) // 2):  # two flipped bits, same size
        data[i] ^= 0x10
    path.write_bytes(bytes(data))
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert counter.ran == ["gyro"]  # recomputed, not reused
    assert "is damaged (calibration.arrow: content does not match its digest)" in caplog.text
    assert (out / "s1" / "calibration.json").read_text() == first
    path.write_bytes(b"truncated")
    registry, counter = toy_registry()
    _run(registry, session, toy_pipeline, out)
    assert counter.ran == ["gyro"] and (out / "s1" / "calibration.json").read_text() == first


def test_a_cold_run_reads_the_outputs_it_produced_without_loading_them_again(
    tmp_path, toy_registry, toy_pipeline, session, monkeypatch
):
    loaded = []
    load = Cache.load
    monkeypatch.setattr(Cache, "load", lambda self, key, port: loaded.append(port) or load(self, key, port))
    out = tmp_path / "out"
    _run(toy_registry()[0], session, toy_pipeline, out)
    assert (out / "s1" / "calibration.json").is_file()
    assert loaded == []  # every stage ran: downstream stages and exports got its tables as returned
    registry, counter = toy_registry(bias_version="7")  # scaled cached, its consumers run
    _run(registry, session, toy_pipeline, out)
    assert counter.cached == ["scaled"] and "samples" in loaded  # a cached output comes from the cache


def test_a_table_digest_is_remembered_while_the_table_lives(monkeypatch):
    import gc

    import pyarrow as pa

    from imupipe import io

    table = pa.table({"x": [1.0, 2.0]})
    digest = table_digest(table)
    equal = pa.concat_tables([table.slice(0, 1), table.slice(1)])  # same content, two chunks
    assert table_digest(equal) == digest
    monkeypatch.setattr(io.ipc, "new_stream", None)  # a second digest of either is not computed
    assert table_digest(table) == table_digest(equal) == digest
    monkeypatch.undo()
    key = id(table)
    del table, equal
    gc.collect()
    assert key not in io._DIGESTS
    assert table_digest(pa.table({"x": [1.0, 3.0]})) != digest

"""Cache keys follow the reader and plugin distributions, not only the bytes and the stages.

A different reader (forced, or named by a manifest), a new version of the
distribution a reader, stage or solver comes from: each reruns exactly what it
feeds, and ``imupipe status`` says which one changed.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
from pipeline_toys import (
    TOY_PIPELINE,
    ArrowSessionReader,
    status_lines,
    write_csv,
    write_manifest,
)

import imupipe.readers
from imupipe.hookspecs import hookimpl
from imupipe.pipeline.api import run_sessions, status
from imupipe.pipeline.cache import session_digest
from imupipe.readers.manifest import ManifestReader


def _run(registry, session, pipeline, out):
    return run_sessions([session], pipeline, out, quiet=True, registry=registry)


_lines = status_lines


def with_dist(registry, kind: str, name: str, dist: str, version: str):
    """Pretend component ``name`` came from distribution ``dist`` at ``version``."""
    component = registry.components[kind][name]
    registry.components[kind][name] = dataclasses.replace(
        component, distribution=dist, dist_version=version
    )
    return registry


class OtherReader(ArrowSessionReader):
    name = "arrowsession_other"

    def sniff(self, path, head):
        return False  # only when forced

    @hookimpl
    def imupipe_register_readers(self, register):
        register(self)


def test_forcing_another_reader_reruns_the_session_stages(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    _run(toy_registry(OtherReader())[0], session, toy_pipeline, out)
    toy_pipeline.write_text(TOY_PIPELINE.replace(
        'description = "toy stages for the pipeline tests"',
        'description = "forced"\n[input]\nreader = "arrowsession_other"',
    ))
    registry, counter = toy_registry(OtherReader())
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["gyro"] == (
        "stale input 'samples' changed (reader changed arrowsession -> arrowsession_other)"
    )
    _run(registry, session, toy_pipeline, out)
    # every stage reading a session stream reruns (accel reads session.temperature)
    assert sorted(counter.ran) == ["accel", "gyro", "mag", "scaled"]
    manifest = json.loads((out / "s1" / "run.json").read_text())
    assert manifest["reader"]["name"] == "arrowsession_other"


def test_reader_distribution_upgrade_reruns_and_status_says_so(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    registry, _ = toy_registry()
    _run(with_dist(registry, "readers", "arrowsession", "imupipe-toy", "1.0"), session,
         toy_pipeline, out)
    registry, counter = toy_registry()
    with_dist(registry, "readers", "arrowsession", "imupipe-toy", "1.1")
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["mag"] == "stale input 'samples' changed (reader arrowsession changed 1.0 -> 1.1)"
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "gyro", "mag", "scaled"]

    registry, counter = toy_registry()  # and the same version again: all cached
    _run(with_dist(registry, "readers", "arrowsession", "imupipe-toy", "1.1"), session,
         toy_pipeline, out)
    assert counter.ran == []


def test_a_reader_a_manifest_delegates_to_is_part_of_the_key(tmp_path, toy_registry):
    data = tmp_path / "data"
    data.mkdir()
    # a canonical CSV, handed to the csv reader by the manifest
    write_csv(data / "acc.csv", np.tile([0.1, 0.2, 9.9], (50, 1)),
              header="t_ns,accel_x,accel_y,accel_z")
    manifest = write_manifest(
        data / "session.toml", "lab", {"stream": "accel", "file": "acc.csv", "reader": "csv"}
    )
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(TOY_PIPELINE)
    out = tmp_path / "out"
    registry, counter = toy_registry(imupipe.readers)
    _run(with_dist(registry, "readers", "csv", "imupipe", "0.1.0"), manifest, pipeline, out)
    assert sorted(counter.ran) == ["accel", "scaled"]

    registry, counter = toy_registry(imupipe.readers)
    with_dist(registry, "readers", "csv", "imupipe", "0.2.0")  # a release with a csv reader fix
    lines = _lines(status([manifest], pipeline, out, registry=registry))
    assert lines["scaled"] == (
        "stale input 'samples' changed "
        "(manifest reader csv changed 'imupipe 0.1.0' -> 'imupipe 0.2.0')"
    )
    _run(registry, manifest, pipeline, out)
    # the table came out the same: accel is reused (early cutoff)
    assert counter.ran == ["scaled"] and counter.cached == ["accel"]


def test_stage_and_solver_plugin_upgrades_rerun_what_they_compute(
    tmp_path, toy_registry, toy_pipeline, session
):
    out = tmp_path / "out"
    registry, _ = toy_registry()
    with_dist(registry, "stages", "toy_bias_gyro", "imupipe-toy", "1.0")
    _run(with_dist(registry, "solvers", "toy_mean", "imupipe-toy", "1.0"), session,
         toy_pipeline, out)

    registry, counter = toy_registry()
    with_dist(registry, "stages", "toy_bias_gyro", "imupipe-toy", "1.1")
    with_dist(registry, "solvers", "toy_mean", "imupipe-toy", "1.0")
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["gyro"] == "stale plugin imupipe-toy dist version changed 1.0 -> 1.1"
    assert lines["mag"] == "fresh"
    _run(registry, session, toy_pipeline, out)
    assert counter.ran == ["gyro"]

    registry, counter = toy_registry()
    with_dist(registry, "stages", "toy_bias_gyro", "imupipe-toy", "1.1")
    with_dist(registry, "solvers", "toy_mean", "imupipe-toy", "2.0")
    lines = _lines(status([session], toy_pipeline, out, registry=registry))
    assert lines["mag"] == "stale solver toy_mean plugin imupipe-toy dist version changed 1.0 -> 2.0"
    _run(registry, session, toy_pipeline, out)
    assert sorted(counter.ran) == ["accel", "gyro", "mag"]


def test_imupipe_own_components_are_keyed_by_their_version_only(toy_registry, tmp_path):
    from imupipe.pipeline.cache import distribution

    registry, _ = toy_registry()
    with_dist(registry, "stages", "toy_scale", "imupipe", "0.1.0")
    assert distribution(registry, "stages", "toy_scale") is None  # a release reruns nothing
    with_dist(registry, "stages", "toy_scale", "imupipe-toy", "3")
    assert distribution(registry, "stages", "toy_scale") == {"name": "imupipe-toy", "version": "3"}


def test_manifest_naming_an_absolute_file_runs(tmp_path, toy_registry):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    acc = write_csv(elsewhere / "acc.csv", np.tile([0.1, 0.2, 9.9], (50, 1)))
    folder = tmp_path / "session"
    folder.mkdir()
    manifest = write_manifest(
        folder / "session.toml", "abs", {"stream": "accel", "file": str(acc.resolve())}
    )
    before = session_digest(manifest, ManifestReader())
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(TOY_PIPELINE)
    registry, _ = toy_registry(imupipe.readers)
    written = _run(registry, manifest, pipeline, tmp_path / "out")
    assert written == [tmp_path / "out" / "session" / "calibration.json"]
    write_csv(acc, np.tile([0.1, 0.2, 9.8], (50, 1)))
    assert session_digest(manifest, ManifestReader()) != before  # the absolute file's bytes count

"""Run a pipeline on one session: stages in topological order, through the cache.

For every stage the runner gathers its input digests, computes its cache key,
and either takes the outputs from the cache or reads the inputs, checks each
table against the schema the stage declares, calls ``func(inputs, params,
solver)``, checks the outputs and stores them. The recording is read only when
a stage has to run. Stages whose required session streams are missing are
skipped with everything downstream (a logged note, and a line in the manifest).

Warnings a stage gives (``warnings.warn``) are caught, logged as one line each
(``<stage>: <message>``), recorded in the run manifest and in the cache entry,
and logged again whenever the entry is reused.
"""

from __future__ import annotations

import copy
import logging
import re
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pyarrow as pa

from .. import __version__, schemas
from ..errors import ImupipeError, SchemaError, SolverError
from ..ingest import check_rate, check_session_path, read_recording, sections_table, stream_facts
from ..plugins import Registry
from .cache import (
    Cache,
    claimant,
    key_parts,
    read_manifest,
    reader_identity,
    session_digest,
    stream_digest,
    write_manifest,
)
from .dag import Node, Pipeline, Ref

log = logging.getLogger("imupipe.pipeline")


@dataclass
class StageRecord:
    """What happened to one stage: ``status`` is ran, cached, skipped or failed."""

    status: str
    key: str = ""
    parts: dict | None = None
    outputs: dict[str, str] = field(default_factory=dict)  # port -> digest
    reason: str = ""
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)  # what the stage warned (also if cached)

    def to_dict(self) -> dict:
        return {
            "status": self.status,
            "key": self.key,
            "parts": self.parts,
            "outputs": self.outputs,
            "reason": self.reason,
            "seconds": round(self.seconds, 6),
            "warnings": list(self.warnings),
        }


@dataclass
class SessionRun:
    """The outcome of a pipeline on a session; ``table(ref)`` loads an output on demand."""

    session: Path
    pipeline: Pipeline
    cache: Cache
    records: dict[str, StageRecord] = field(default_factory=dict)
    _tables: dict[str, pa.Table] = field(default_factory=dict)
    source: _Source | None = None

    def keep(self, stage: str, outputs: Mapping[str, pa.Table]) -> None:
        """The outputs a stage just returned (and the cache stored): later stages and the exports
        read them as they are, not again from the cache (a long recording's per-sample table:
        its bytes read, verified and digested once more)."""
        self._tables.update({str(Ref(stage, port)): table for port, table in outputs.items()})

    def table(self, ref: Ref) -> pa.Table | None:
        """An output of a stage that ran or was cached; None if the stage was skipped."""
        rec = self.records.get(ref.source)
        if rec is None or rec.status not in ("ran", "cached"):
            return None
        name = str(ref)
        if name not in self._tables:
            self._tables[name] = self.cache.load(rec.key, ref.port)
        return self._tables[name]

    @property
    def skipped(self) -> dict[str, str]:
        return {k: r.reason for k, r in self.records.items() if r.status == "skipped"}

    @property
    def raw_units(self) -> dict[str, str]:
        """Stream -> unit of its raw values where a reader left them unconverted ("counts")."""
        return self.source.raw_units() if self.source is not None else {}

    @property
    def stream_facts(self) -> dict[str, dict]:
        """Stream -> what exporters need of it (``ingest.stream_facts``): rate, topic, ..."""
        return self.source.facts() if self.source is not None else {}


RAW_UNIT_KEY = b"imupipe.raw_unit"  # table metadata: the values are in this unit, not SI


class _Source:
    """The session's raw streams, read only when first needed."""

    def __init__(self, path: Path, pipeline: Pipeline, registry: Registry, previous: dict | None):
        self.path, self.pipeline, self.registry = path, pipeline, registry
        reader = claimant(registry, path, pipeline.reader)
        self.reader = reader_identity(registry, reader, path)
        self.digest = digest = session_digest(path, reader)
        self._streams: dict[str, pa.Table] | None = None
        self._names: list[str] | None = None
        self._units: dict[str, str] | None = None
        self._facts: dict[str, dict] | None = None
        if (
            previous
            and previous.get("session_digest") == digest
            and previous.get("device") == pipeline.device
            and previous.get("reader") == self.reader
            and previous.get("streams") is not None  # None: that run failed reading it
        ):
            # known from the last run of the same bytes through the same reader
            self._names = list(previous["streams"])
            self._units = previous.get("raw_units")
            self._facts = previous.get("stream_facts")

    def _read(self) -> dict[str, pa.Table]:
        if self._streams is None:
            recording = read_recording(self.path, self.registry, self.pipeline.reader)
            self._streams = dict(recording.device(self.pipeline.device))
            for name, table in self._streams.items():
                check_rate(table, name, f"{self.path} [{name}]")
            if recording.meta.get("sections"):  # a manifest's [sections]: session.sections
                self._streams["sections"] = sections_table(recording.meta["sections"])
            self._names = sorted(self._streams)
            self._units = {
                name: unit.decode()
                for name, table in sorted(self._streams.items())
                if (unit := (table.schema.metadata or {}).get(RAW_UNIT_KEY))
            }
            self._facts = stream_facts(self._streams)
        return self._streams

    def names(self) -> list[str]:
        if self._names is None:
            self._read()
        return list(self._names or [])

    def raw_units(self) -> dict[str, str]:
        if self._units is None:
            self._read()
        return dict(self._units or {})

    def facts(self) -> dict[str, dict]:
        if self._facts is None:
            self._read()
        return dict(self._facts or {})

    def table(self, stream: str) -> pa.Table:
        return self._read()[stream]


def run_session(
    session: Path,
    pipeline: Pipeline,
    registry: Registry,
    cache: Cache,
    manifest_path: Path,
    on_stage: Callable[[str, StageRecord], None] | None = None,
) -> SessionRun:
    """Run ``pipeline`` on ``session``; write the run manifest (also when a stage fails)."""
    session = check_session_path(Path(session))
    if session.is_dir():
        raise ImupipeError(
            f"{session}: is a directory; give a recording file or a session.toml "
            "(imupipe batch takes folders)"
        )
    run = SessionRun(session, pipeline, cache)
    source = None
    error = None
    try:
        # choosing the reader may fail (no reader claims the file): recorded like any error
        source = run.source = _Source(session, pipeline, registry, read_manifest(manifest_path))
        for key, node in pipeline.nodes.items():
            record = _run_node(node, run, source, registry)
            run.records[key] = record
            if on_stage is not None:
                on_stage(key, record)
    except BaseException as exc:
        error = f"{type(exc).__name__}: {exc}"
        raise
    finally:
        write_manifest(
            manifest_path,
            {
                "session": str(session.resolve()),
                "session_digest": source.digest if source else None,
                "device": pipeline.device,
                "reader": source.reader if source else None,
                "streams": source._names if source else None,
                "raw_units": source._units if source else None,
                "stream_facts": source._facts if source else None,
                "pipeline": {"name": pipeline.name, "path": str(Path(pipeline.path).resolve()),
                             **({"overrides": list(pipeline.overrides)} if pipeline.overrides else {})},
                "imupipe_version": __version__,
                "error": error,
                "stages": {k: r.to_dict() for k, r in run.records.items()},
            },
        )
    return run


def _run_node(node: Node, run: SessionRun, source: _Source, registry: Registry) -> StageRecord:
    digests: dict[str, str] = {}
    for port, ref in node.inputs.items():
        found, why = _input_digest(ref, run, source)
        if found is not None:
            digests[port] = found
        elif port not in node.stage.optional_inputs:
            log.info("%s: skipping stage %r: %s", source.path, node.key, why)
            return StageRecord("skipped", reason=why)
    parts = key_parts(node, digests)
    key = parts.key
    cached = run.cache.entry(key)
    if cached is not None:
        _log_warnings(node.key, cached["warnings"])  # said again: the result still has them
        _observe(registry, "imupipe_after_stage", stage=node.key, key=key, cached=True, seconds=0.0)
        return StageRecord(
            "cached", key, parts.to_dict(), cached["outputs"], warnings=cached["warnings"]
        )

    _observe(registry, "imupipe_before_stage", stage=node.key, key=key)
    where = f"{source.path}: stage {node.key!r} ({node.stage.name})"
    inputs = {}
    for port in digests:
        ref = node.inputs[port]
        table = source.table(ref.port) if ref.is_session else run.table(ref)
        schemas.check(table, node.stage.inputs[port], f"{where} input {port!r}")
        inputs[port] = table
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            outputs = node.stage.func(MappingProxyType(inputs), node.params, node.solver)
        except ImupipeError as exc:
            raise _prefixed(exc, where + _missing_imu(run.pipeline, source)) from exc
        except NUMERICAL_ERRORS as exc:  # the data cannot determine what the stage solves for
            raise SolverError(
                f"{where}: the data cannot determine this stage's result ({type(exc).__name__}: "
                f"{exc}); check for dead, saturated or constant axes and the units of the data"
            ) from exc
        finally:
            # numpy's floating-point warnings (divide by zero, ...) are symptoms, not news: the
            # stage's own checks or the error that follows say what is wrong; kept at debug level
            for w in caught:
                if _is_numpy_fp_warning(w):
                    log.debug("%s: %s", node.key, w.message)
            said = list(dict.fromkeys(str(w.message) for w in caught
                                      if not _is_numpy_fp_warning(w)))
            _log_warnings(node.key, said)
    seconds = time.perf_counter() - t0
    _check_outputs(node, outputs, where)
    produced = {p: outputs[p] for p in node.stage.outputs}
    stored = run.cache.store(parts, produced, node.key, said)
    run.keep(node.key, produced)
    _observe(registry, "imupipe_after_stage", stage=node.key, key=key, cached=False,
             seconds=seconds)
    return StageRecord("ran", key, parts.to_dict(), stored, seconds=seconds, warnings=said)


NUMERICAL_ERRORS = (np.linalg.LinAlgError, FloatingPointError, OverflowError, ZeroDivisionError)
_NUMPY_FP = re.compile(r"(invalid value|divide by zero|overflow|underflow) encountered|"
                       r"Mean of empty slice|Degrees of freedom <= 0|All-NaN")


def _is_numpy_fp_warning(w: warnings.WarningMessage) -> bool:
    return issubclass(w.category, RuntimeWarning) and bool(_NUMPY_FP.search(str(w.message)))


def _observe(registry: Registry, hook: str, **kwargs) -> None:
    """Call a lifecycle hook (they observe, never change data) of every plugin; one that
    raises is that plugin's failure: said once, the plugin listed broken, the run goes on."""
    for impl in reversed(getattr(registry.pm.hook, hook).get_hookimpls()):
        name = registry.pm.get_name(impl.plugin) or repr(impl.plugin)
        if name in registry.broken:
            continue
        try:
            impl.function(**{a: kwargs[a] for a in impl.argnames if a in kwargs})
        except Exception as exc:  # noqa: BLE001 - a plugin's observer must not stop the run
            registry.broken[name] = ("", "", f"{hook} raised {type(exc).__name__}: {exc}")
            log.warning("plugin %r: %s raised %s: %s; its lifecycle hooks are ignored from now on",
                        name, hook, type(exc).__name__, exc)


def _log_warnings(stage: str, messages: list[str]) -> None:
    for message in messages:
        log.warning("%s: %s", stage, message)


def _input_digest(ref: Ref, run: SessionRun, source: _Source) -> tuple[str | None, str]:
    """The content digest of an input, or None and why it is unavailable."""
    if ref.is_session:
        if ref.port not in source.names():
            return None, f"the session has no {ref.port!r} stream"
        return stream_digest(source.digest, run.pipeline.device, ref.port, source.reader), ""
    rec = run.records[ref.source]
    if rec.status not in ("ran", "cached"):
        return None, f"upstream stage {ref.source!r} was skipped ({rec.reason})"
    return rec.outputs[ref.port], ""


def _check_outputs(node: Node, outputs: object, where: str) -> None:
    if not isinstance(outputs, dict):
        raise SchemaError(
            f"{where}: returned {type(outputs).__name__}, expected a dict of tables "
            f"({', '.join(node.stage.outputs)})"
        )
    missing = [p for p in node.stage.outputs if p not in outputs]
    extra = [p for p in outputs if p not in node.stage.outputs]
    if missing or extra:
        raise SchemaError(
            f"{where}: returned outputs {sorted(outputs)}, declared "
            f"{sorted(node.stage.outputs)}; fix the stage or its declaration"
        )
    for port, schema_id in node.stage.outputs.items():
        schemas.check(outputs[port], schema_id, f"{where} output {port!r}")


def _missing_imu(pipeline: Pipeline, source: _Source) -> str:
    """`` (the session has no accel/gyro stream ...)`` when the pipeline reads one that is
    missing: the likely cause of a stage's failure (an MCAP without its Imu topic)."""
    used = {ref.port for node in pipeline.nodes.values() for ref in node.inputs.values()
            if ref.is_session}
    missing = [s for s in ("accel", "gyro") if s in used and s not in source.names()]
    if not missing:
        return ""
    return (f" (the session has no {' or '.join(missing)} stream: for ROS/MCAP, no "
            f"sensor_msgs/Imu topic; it has {', '.join(source.names()) or 'none'})")


def _prefixed(exc: ImupipeError, where: str) -> ImupipeError:
    """The same error, of the same class, with ``where`` in front of its message."""
    new = copy.copy(exc)
    new.args = (f"{where}: {exc}",)
    return new

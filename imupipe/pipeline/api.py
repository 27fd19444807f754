"""What the command line calls: ``run_sessions``, ``batch``, ``status``.

Output layout (``docs/pipelines.md``)::

    <out>/.cache/                    content-addressed stage outputs, shared by all sessions
    <out>/<session-id>/run.json      run manifest: each stage's key parts, status, outputs
    <out>/<session-id>/calibration.json
    <out>/<session-id>/...           files of the "report" exporter, if one is registered

``<session-id>`` is the file's stem (for a ``session.toml`` manifest, its
folder's name), made unique with a short hash when two sessions share it.
"""

from __future__ import annotations

import glob
import hashlib
import logging
import os
import traceback
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__
from ..errors import ImupipeError, MissingExtraError
from ..heap import release_free_memory
from ..io import remove
from ..paths import check_out_dir, safe_name, under
from ..plugins import Registry, make_registry
from ..progress import progress
from ..threads import blas_threads as check_blas_threads
from ..threads import limited_blas
from ..verdict import read_verdict
from .cache import (
    Cache,
    claimant,
    distribution,
    read_manifest,
    reader_identity,
    session_digest,
    write_manifest,
)
from .config import default_pipeline_path, load_pipeline
from .dag import Pipeline, Ref
from .export import EXPORT_DIR, ExportError, export_formats, noise_tables, parse_formats
from .export_cache import cacheable, export_key, in_place, run_cached, table_digests
from .runner import SessionRun, run_session
from .status import render, stage_states

log = logging.getLogger("imupipe.pipeline")

CACHE_DIR = ".cache"
FIGURES_DIR = "figures"  # in CACHE_DIR: the report's figures by their key
MANIFEST = "run.json"
CALIBRATION = "calibration.json"
FOLDER_SESSIONS = ("session.toml", "metadata.yaml")  # files that stand for their whole folder


@dataclass(frozen=True)
class RegistrySpec:
    """How a worker process makes its registry: plugin modules by import name; entry points?"""

    plugins: tuple[str, ...] = ()
    entry_points: bool = True

    def make(self) -> Registry:
        import importlib

        return make_registry(
            [importlib.import_module(m) for m in self.plugins], entry_points_too=self.entry_points
        )


DEFAULT_SPEC = RegistrySpec()  # what ``imupipe batch`` workers load: every installed plugin


@dataclass(frozen=True)
class Job:
    """One session of a batch (picklable)."""

    session: str
    session_id: str
    pipeline: str
    out: str
    registry: RegistrySpec = field(default_factory=RegistrySpec)
    export: tuple[str, ...] = ()  # format exporters (``--export``)
    overrides: tuple[str, ...] = ()  # ``--set STAGE.PARAM=VALUE`` (and ``--device``)
    blas_threads: int | None = None  # None: the worker's $IMUPIPE_BLAS_THREADS, else 1

    def failed(self, reason: str) -> JobResult:
        return JobResult(self.session, "failed", reason)


@dataclass(frozen=True)
class JobResult:
    session: str
    status: str  # ok | failed
    detail: str  # the calibration.json written, or why the session failed
    verdict: str = ""  # pass | warn | fail of the calibration written (imupipe.verdict)


# --------------------------------------------------------------------------- one session


def session_ids(sessions: Sequence[Path]) -> list[str]:
    """A folder name per session: the stem (a manifest's folder name), unique within the list.

    The stem is made a safe folder name (``paths.safe_name``: never ``..``, a
    separator or hidden); names that then coincide (case aside) get a hash of the
    session's path.
    """

    def stem(p: Path) -> str:
        return _resolved(p.parent).name if p.name.lower() in FOLDER_SESSIONS else p.stem

    stems = [safe_name(stem(Path(s)), "session") for s in sessions]
    folded = [s.lower() for s in stems]
    out = []
    for s, path in zip(stems, sessions, strict=True):
        if folded.count(s.lower()) > 1:
            s = f"{s}-{hashlib.sha256(str(_resolved(path)).encode()).hexdigest()[:8]}"
        out.append(s)
    return out


def _resolved(path: Path | str) -> Path:
    """``path`` resolved; as an absolute path when it cannot be (a loop of links: said later)."""
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError):
        return Path(os.path.abspath(path))


def process_session(
    session: Path, session_id: str, pipeline: Pipeline, registry: Registry, out: Path, on_stage=None,
    export: Sequence[str] = (),
) -> Path | None:
    """Run ``pipeline`` on one session and export; return the calibration.json written (if any).

    Exporters write into a private staging folder ``<session-id>/.part-<pid>-<token>/``
    that is moved into place only when every one of them has succeeded: a failing
    run leaves the previous result (or a concurrent run's) exactly as it was and
    removes only its own staging folder (run.json records the error for ``status``).
    Staging folders and ``.part`` files left by a killed run are removed by the next.
    """
    out = Path(out)
    run_dir = under(out, session_id)
    cache = Cache(under(out, CACHE_DIR))
    remove_stale_parts(run_dir)
    remove_stale_parts(cache.root, depth=3)
    run = run_session(session, pipeline, registry, cache, run_dir / MANIFEST, on_stage)
    # a warm run: every export in place as made from these tables, and no export/ to clear
    if not export and not (run_dir / EXPORT_DIR).exists() and \
            (done := _exports_in_place(run, registry, run_dir)) is not None:
        return done
    staging = _staging_dir(run_dir)
    release_free_memory()  # the stages' freed arrays: the figures could not reuse them
    try:
        written = _export(run, registry, staging, export)
    except ExportError:  # the calibration stands; only a requested format could not be written
        _commit(staging, run_dir)
        raise
    except BaseException as exc:
        remove(staging)
        _record_error(run_dir / MANIFEST, f"{type(exc).__name__}: {exc}")
        raise
    _commit(staging, run_dir)
    return None if written is None else run_dir / Path(written).relative_to(staging)


PART = ".part"


def _record_error(manifest_path: Path, error: str) -> None:
    """Say in run.json that the run failed after its stages (while exporting)."""
    manifest = read_manifest(manifest_path)
    if manifest is not None and not manifest.get("error"):
        manifest.pop("format", None)
        write_manifest(manifest_path, {**manifest, "error": error})


def _staging_dir(run_dir: Path) -> Path:
    import os
    import secrets

    staging = under(run_dir, f"{PART}-{os.getpid()}-{secrets.token_hex(4)}")
    staging.mkdir(parents=True)
    return staging


def _commit(staging: Path, run_dir: Path) -> None:
    """Move every staged file or folder into ``run_dir``; ``export/`` always follows calibration.json."""
    import os

    try:
        names = sorted(p.name for p in staging.iterdir())
        if EXPORT_DIR not in names:  # no format asked for this time: none stays from before
            old = under(run_dir, EXPORT_DIR)
            if old.exists() or old.is_symlink():
                _remove_aside(old, staging)
        for name in names:
            src, dst = staging / name, under(run_dir, name)
            if src.is_dir():
                for _ in range(5):  # a concurrent run may put its own in place meanwhile
                    if dst.exists() or dst.is_symlink():
                        _remove_aside(dst, staging)
                    try:
                        os.rename(src, dst)
                        break
                    except OSError:
                        continue
                else:
                    raise ImupipeError(f"{dst}: could not be replaced (another run keeps writing it)")
            else:
                os.replace(src, dst)
    finally:
        remove(staging)


def _remove_aside(path: Path, staging: Path) -> None:
    """Remove ``path`` by first renaming it into the staging folder (a reader never sees half)."""
    import os
    import secrets

    aside = staging / f"{PART}-old-{secrets.token_hex(4)}"
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return
    remove(aside)


def remove_stale_parts(folder: Path, depth: int = 1) -> None:
    """Remove staging folders and ``.part`` files under ``folder`` left by runs no longer alive.

    Their names carry the writer's process id (``.part-<pid>-...``, ``.<name>.<pid>.<x>.part``);
    one whose process still runs is a concurrent run's and is left alone, unless a day old.
    """
    import time

    folder = Path(folder)
    if not folder.is_dir():
        return
    candidates = [p for d in range(depth) for p in folder.glob("/".join(["*"] * d + [".*"]))
                  if p.name.startswith(f"{PART}-") or p.name.endswith(PART)]
    now = time.time()
    for p in candidates:
        pid = _part_pid(p.name)
        try:
            old = now - p.lstat().st_mtime > 86400
        except FileNotFoundError:
            continue
        if old or pid is None or not _alive(pid):
            remove(p)


def _part_pid(name: str) -> int | None:
    import re

    m = re.match(r"^\.part-(\d+)-", name) or re.search(r"\.(\d+)\.[^.]*\.part$", name)
    return int(m.group(1)) if m else None


def _alive(pid: int) -> bool:
    import os

    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def export_context(session: str, pipeline: Pipeline, stages: dict[str, dict],
                   raw_units: dict[str, str] | None) -> dict:
    """What every exporter is told besides its tables and the verdict (part of the cache key)."""
    return {
        "session": session,
        "pipeline": pipeline.name,
        "imupipe_version": __version__,
        "skipped": {k: r.get("reason", "") for k, r in stages.items() if r.get("status") == "skipped"},
        "raw_units": dict(raw_units or {}),  # stream -> unit of raw values not in SI ("counts")
    }


def verdict_inputs(stages: dict[str, dict], stream_facts: dict | None) -> dict:
    """What the verdict is made from (``run_verdict``): every stage output's digest and the
    streams' facts; in the export cache key instead of the verdict itself, so that a warm run
    or batch decides from run.json alone, without computing it."""
    return {"outputs": {k: r.get("outputs") or {} for k, r in sorted(stages.items())},
            "stream_facts": stream_facts or {}}


def _exporters(pipeline: Pipeline, registry: Registry) -> list[tuple[str, object, tuple]]:
    """(name, exporter, the refs of the tables it gets) of the pipeline's exports, in order."""
    out = []
    if pipeline.export_calibration:
        terms = tuple(r for r in pipeline.export_reports  # imupipe diagnose: model_terms
                      if r.source in pipeline.nodes
                      and pipeline.nodes[r.source].stage.outputs.get(r.port) == "diagnosis")
        out.append(("calibration_json", registry.get("exporters", "calibration_json"),
                    pipeline.export_calibration + terms))
    if pipeline.export_reports:
        for name in ("residual_map", "diagnosis", "noise_json", "report"):  # only report needs an extra
            if name in registry.names("exporters"):
                out.append((name, registry.get("exporters", name), pipeline.export_reports))
            elif name == "report":
                log.info("no 'report' exporter is registered; skipping the reports")
    return out


def _export_key(name: str, exporter, refs, stages: dict, context: dict, verdict: dict,
                registry: Registry) -> str:
    return export_key(name, exporter, distribution(registry, "exporters", name),
                      table_digests(refs, stages), {**context, "verdict_inputs": verdict})


def _exports_in_place(run: SessionRun, registry: Registry, run_dir: Path) -> Path | None:
    """The calibration.json when every export's files are in ``run_dir`` as made from this
    run's tables (nothing to rewrite), else None."""
    pipeline = run.pipeline
    if not pipeline.export_calibration:
        return None
    stages = {k: r.to_dict() for k, r in run.records.items()}
    context = export_context(str(run.session), pipeline, stages, run.raw_units)
    verdict = verdict_inputs(stages, run.stream_facts)
    for name, exporter, refs in _exporters(pipeline, registry):
        key = _export_key(name, exporter, refs, stages, context, verdict, registry)
        if not cacheable(exporter) or in_place(run_dir, name, key) is None:
            return None
    return run_dir / CALIBRATION


def _export(run: SessionRun, registry: Registry, run_dir: Path, formats: Sequence[str] = ()
            ) -> Path | None:
    """Write the pipeline's exports (through the export cache) and the formats asked for."""
    pipeline = run.pipeline
    stages = {k: r.to_dict() for k, r in run.records.items()}
    context = export_context(str(run.session), pipeline, stages, run.raw_units)
    verdict = verdict_inputs(stages, run.stream_facts)
    calibration = {}
    full: dict = {}

    def full_context() -> dict:  # the verdict is computed only when an exporter has to run
        if not full:
            # figures by what they are drawn from: a report redrawn because one table changed
            # copies the others (report.exporter.figure_key)
            full.update(context, figure_store=str(run.cache.root / FIGURES_DIR))
            calibration.update({str(r): t for r in pipeline.export_calibration
                                if (t := run.table(r)) is not None})
            if calibration:
                full["verdict"] = run_verdict(run, calibration, context["raw_units"])
        return full

    written = None
    for name, exporter, refs in _exporters(pipeline, registry):
        def tables(refs=refs):
            return {str(r): t for r in refs if (t := run.table(r)) is not None}

        key = _export_key(name, exporter, refs, stages, context, verdict, registry)
        try:
            paths = run_cached(name, exporter, key, tables, full_context, run_dir, run.cache.root)
        except MissingExtraError as exc:  # the calibration stands; say how to get reports
            if name != "report":
                raise
            warnings.warn(f"{run.session}: no report written: {exc}", stacklevel=2)
            continue
        if name == "calibration_json":
            written = paths[0]
    # export/ always matches calibration.json: cleared on every run, then the formats asked for
    results = {}
    if formats:
        context = {**full_context(), "stream_facts": run.stream_facts, "device": pipeline.device}
        noise = {f"{k}.{p}": run.table(Ref(k, p)) for k, node in pipeline.nodes.items()
                 for p, sid in node.stage.outputs.items() if sid == "noise"}
        results = {**calibration, **noise_tables({k: t for k, t in noise.items() if t is not None})}
    export_formats(formats, results, context, run_dir, registry)
    return written


def up_to_date(session: Path, session_id: str, pipeline: Pipeline, registry: Registry, out: Path
               ) -> Path | None:
    """The calibration.json of a session with nothing to recompute or rewrite, else None.

    Nothing to recompute: its last run (run.json, no error, the same pipeline file)
    has every stage fresh or skipped (``imupipe status``), and every export's files
    are in the session folder as made from the same tables (``export_cache``).
    Decided from the session's digest and the run manifest; no table is read.
    """
    run_dir = Path(out) / session_id
    manifest = read_manifest(run_dir / MANIFEST)
    if not manifest or manifest.get("error") or not pipeline.export_calibration:
        return None
    if (manifest.get("pipeline") or {}).get("path") != str(Path(pipeline.path).resolve()):
        return None
    cache = Cache(Path(out) / CACHE_DIR)
    states = stage_states(pipeline, Path(session), manifest, cache,
                          *_reader_now(Path(session), pipeline, registry))
    if any(s.state not in ("fresh", "skipped") for s in states):
        return None
    stages = manifest.get("stages") or {}
    context = export_context(str(session), pipeline, stages, manifest.get("raw_units"))
    verdict = verdict_inputs(stages, manifest.get("stream_facts"))
    for name, exporter, refs in _exporters(pipeline, registry):
        if not cacheable(exporter):
            return None
        key = _export_key(name, exporter, refs, stages, context, verdict, registry)
        if in_place(run_dir, name, key) is None:
            return None
    return run_dir / CALIBRATION


VERDICT_SCHEMAS = ("validation", "control_errors", "events", "residual_map", "rests")


def run_verdict(run: SessionRun, calibration: dict, raw_units: dict) -> dict:
    """``verdict.judge`` on what the run produced: the calibration as exported, every output
    of a schema the checks read (the reports' rests first), and the streams' facts."""
    from ..exporters import with_raw_units
    from ..models import Calibration
    from ..schemas import schema_of
    from ..verdict import judge

    doc = with_raw_units(Calibration.from_tables(*calibration.values()).to_dict(), raw_units)
    tables = {str(r): t for r in run.pipeline.export_reports
              if (t := run.table(r)) is not None and schema_of(t) == "rests"}
    for name, node in run.pipeline.nodes.items():
        for port, sid in node.stage.outputs.items():
            ref = Ref(name, port)
            if sid in VERDICT_SCHEMAS and sid != "rests" and (t := run.table(ref)) is not None:
                tables[str(ref)] = t
    if not any(schema_of(t) == "rests" for t in tables.values()):
        tables.update({f"{n}.{p}": t for n, node in run.pipeline.nodes.items()
                       for p, sid in node.stage.outputs.items()
                       if sid == "rests" and (t := run.table(Ref(n, p))) is not None})
    return judge(doc, tables, run.stream_facts)


# --------------------------------------------------------------------------- run


def run_sessions(
    sessions: list[Path],
    pipeline: Path | None = None,
    out: Path = Path("imupipe-out"),
    quiet: bool = False,
    *,
    registry: Registry | None = None,
    export: Sequence[str] = (),
    overrides: Sequence[str] = (),
    diagnose: bool = False,
    blas_threads: int | None = None,
) -> list[Path]:
    """``imupipe run``: every session in turn; a failing session does not stop the others.
    ``diagnose``: the pipeline's residual map stage runs as the diagnosis (``imupipe diagnose``).

    Returns the calibration files written; raises the first session's error
    (naming how many failed) once all have been tried. BLAS runs with
    ``blas_threads`` threads (default ``$IMUPIPE_BLAS_THREADS``, else 1; ``imupipe/threads.py``).
    """
    check_blas_threads(blas_threads)  # a bad value fails before anything is read
    registry = registry or make_registry()
    # bad config: fail before reading any data
    spec = load_pipeline(pipeline, registry, tuple(overrides), diagnose=diagnose)
    export = parse_formats(export, registry)
    check_out_dir(out)
    # the same file named twice is one session
    sessions = list({_resolved(s): Path(s) for s in sessions}.values())
    written, failures = [], []
    with limited_blas(blas_threads), progress(quiet) as p:
        all_task = p.add_task("sessions", total=len(sessions))
        stage_task = p.add_task("stages", total=len(spec.nodes))
        for session, sid in zip(sessions, session_ids(sessions), strict=True):
            p.update(stage_task, completed=0, description=f"{sid}")
            try:
                path = process_session(
                    session,
                    sid,
                    spec,
                    registry,
                    Path(out),
                    on_stage=lambda *_: p.advance(stage_task),
                    export=export,
                )
            except ImupipeError as exc:
                failures.append(exc)
                if len(sessions) > 1:
                    log.error("%s", exc)
            else:
                if path is not None:
                    written.append(path)
            p.advance(all_task)
    if failures:
        first = failures[0]
        if len(sessions) > 1:
            first.args = (f"{first} ({len(failures)} of {len(sessions)} sessions failed)",)
        raise first
    return written


# --------------------------------------------------------------------------- batch


def run_job(job: Job) -> JobResult:
    """Worker: one session in its own process; never raises (a failure is a result)."""
    try:
        registry = job.registry.make()
        spec = load_pipeline(Path(job.pipeline), registry, job.overrides)
        with limited_blas(job.blas_threads):
            path = process_session(Path(job.session), job.session_id, spec, registry, Path(job.out),
                                   export=job.export)
        verdict = (read_verdict(path) or {}).get("status", "") if path else ""
        return JobResult(job.session, "ok", str(path) if path else "(no calibration exported)", verdict)
    except ImupipeError as exc:
        return job.failed(str(exc))
    except Exception as exc:  # noqa: BLE001 - the batch reports it and goes on with the others
        log.debug("%s", traceback.format_exc())
        return job.failed(f"internal error: {type(exc).__name__}: {exc}")


def expand_inputs(inputs: Sequence[str], registry: Registry, out: Path | None = None) -> list[Path]:
    """Session files from directories and globs.

    A directory contributes, recursively, every file that a registered reader
    with its suffix claims (``sniff``), except that a folder holding a
    ``session.toml`` is that one session (its data files are not sessions of
    their own). A file with a reader's suffix that no reader claims is skipped
    with a warning. Hidden folders and ``out`` are never searched. A file named
    explicitly (or matched by a glob) is taken as it is.
    """
    readers = [registry.get("readers", n) for n in registry.names("readers")]
    skip = Path(out).resolve() if out is not None else None
    found: list[Path] = []
    for item in inputs:
        matches = [Path(m) for m in sorted(glob.glob(item, recursive=True))] or (
            [Path(item)] if Path(item).exists() else []
        )
        if not matches:
            raise ImupipeError(f"{item}: no such file, directory or matching glob")
        for m in matches:
            found += _walk(m, readers, skip) if m.is_dir() else [m]
    unique = list(dict.fromkeys(_resolved(p) for p in found))
    if not unique:
        suffixes = sorted({s for r in readers for s in getattr(r, "suffixes", ())})
        raise ImupipeError(
            f"{', '.join(inputs)}: no session files found (suffixes read: "
            f"{', '.join(suffixes) or 'none'})"
        )
    return unique


def _walk(folder: Path, readers: list, skip: Path | None) -> list[Path]:
    if skip is not None and folder.resolve() == skip:
        return []
    for name in FOLDER_SESSIONS:  # a folder that is one session: a manifest, a ROS 2 bag
        manifest = folder / name
        if manifest.is_file():
            return [manifest]
    out = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith("."):
            continue
        if p.is_dir():
            out += _walk(p, readers, skip)
            continue
        candidates = [r for r in readers if p.suffix.lower() in getattr(r, "suffixes", ())]
        if not candidates:
            continue
        if not p.is_file():  # a FIFO, a device, a dangling link or a loop of links
            log.warning("%s: skipped: not a regular file", p)
            continue
        with open(p, "rb") as f:
            head = f.read(64)
        if any(r.sniff(p, head) for r in candidates):
            out.append(p)
        else:
            log.warning(
                "%s: skipped: no reader accepts it (%s)", p, ", ".join(r.name for r in candidates)
            )
    return out


def batch(
    inputs: list[str],
    pipeline: Path | None = None,
    out: Path = Path("imupipe-out"),
    executor: str = "local",
    jobs: int | None = None,
    quiet: bool = False,
    *,
    plugins: RegistrySpec | None = None,
    export: Sequence[str] = (),
    overrides: Sequence[str] = (),
    strict: bool = False,
    blas_threads: int | None = None,
) -> list[JobResult]:
    """``imupipe batch``: each session an independent job; returns the failures (``strict``:
    and the sessions whose verdict is warn or fail).

    Prints a summary table (session, status, output or reason). A session with
    nothing to recompute or rewrite (``up_to_date``) is not dispatched. Each job runs
    its BLAS with ``blas_threads`` threads (default: the worker's
    ``$IMUPIPE_BLAS_THREADS``, else 1), so ``jobs`` workers use ``jobs`` cores.
    """
    check_blas_threads(blas_threads)
    spec = plugins or DEFAULT_SPEC
    registry = spec.make()
    overrides = tuple(overrides)
    pipeline_obj = load_pipeline(pipeline, registry, overrides)  # bad config: fail before any job
    export = parse_formats(export, registry)
    runner = registry.get("executors", executor)
    sessions = expand_inputs(inputs, registry, out)
    check_out_dir(out)
    jobs_list = [
        Job(str(s), sid, str(pipeline_obj.path.resolve()), str(Path(out).resolve()), spec, export,
            overrides, blas_threads)
        for s, sid in zip(sessions, session_ids(sessions), strict=True)
    ]
    # a session with nothing to recompute or rewrite is not sent to a worker at all
    results: list[JobResult | None] = [None] * len(jobs_list)
    if not export:
        for i, job in enumerate(jobs_list):
            try:
                done = up_to_date(Path(job.session), job.session_id, pipeline_obj, registry,
                                  Path(job.out))
            except ImupipeError:
                done = None  # the job says what is wrong
            if done is not None:
                verdict = (read_verdict(done) or {}).get("status", "")
                results[i] = JobResult(job.session, "ok", str(done), verdict)
    todo = [i for i, r in enumerate(results) if r is None]
    if len(todo) < len(jobs_list):
        log.info("%d of %d sessions are up to date", len(jobs_list) - len(todo), len(jobs_list))
    with progress(quiet) as p:
        task = p.add_task(f"sessions ({executor})", total=len(jobs_list))
        p.advance(task, len(jobs_list) - len(todo))
        kwargs = {"on_result": lambda *_: p.advance(task)} if _takes_on_result(runner) else {}
        if todo:
            ran = runner.map(run_job, [jobs_list[i] for i in todo], jobs, **kwargs)
            for i, r in zip(todo, ran, strict=True):
                results[i] = r
    print(summary(results))
    return [r for r in results if r.status != "ok" or (strict and r.verdict not in ("pass", ""))]


def _takes_on_result(executor) -> bool:
    import inspect

    try:
        return "on_result" in inspect.signature(executor.map).parameters
    except (TypeError, ValueError):
        return False


def summary(results: Sequence[JobResult]) -> str:
    """A plain table: session, status, output or reason."""
    rows = [("session", "status", "output / reason")] + [
        (r.session, f"{r.status} ({r.verdict})" if r.verdict else r.status, r.detail) for r in results
    ]
    w0, w1 = (max(len(r[i]) for r in rows) for i in (0, 1))
    failed = sum(r.status != "ok" for r in results)
    lines = [f"{a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows]
    lines.append(f"{len(results) - failed} ok, {failed} failed")
    return "\n".join(lines)


# --------------------------------------------------------------------------- status


def status(
    sessions: list[Path],
    pipeline: Path | None = None,
    out: Path = Path("imupipe-out"),
    *,
    registry: Registry | None = None,
    overrides: Sequence[str] = (),
) -> str:
    """``imupipe status``: per session, which stages are stale and why; nothing runs.

    With no sessions, those recorded in ``out`` (their run manifests). With no
    ``pipeline``, each session is compared with the pipeline its run.json names
    (the default pipeline for a session never run, or when that file is gone), with the
    ``--set`` overrides recorded there unless ``overrides`` are given.
    """
    registry = registry or make_registry()
    overrides = tuple(overrides)
    given = load_pipeline(pipeline, registry, overrides) if pipeline is not None else None
    loaded: dict[tuple, Pipeline] = {}

    def pipeline_for(manifest: dict | None) -> tuple[Pipeline, str]:
        if given is not None:
            return given, ""
        entry = (manifest or {}).get("pipeline") or {}
        recorded, sets = entry.get("path"), tuple(overrides or entry.get("overrides") or ())
        if recorded and Path(recorded).is_file():
            key, note = str(Path(recorded).resolve()), f" from run.json: {recorded}"
        else:
            key = str(default_pipeline_path())
            note = (
                f" (default; {recorded} recorded in run.json is gone)" if recorded else " (default)"
            )
        if sets:
            note += f" with --set {' --set '.join(sets)}"
        if (key, sets) not in loaded:
            loaded[key, sets] = load_pipeline(Path(key), registry, sets)
        return loaded[key, sets], note

    out = Path(out)
    sessions = [Path(s) for s in sessions]
    if sessions:
        pairs = list(zip(sessions, session_ids(sessions), strict=True))
    else:
        pairs = []
        for manifest_path in sorted(out.glob(f"*/{MANIFEST}")):
            manifest = read_manifest(manifest_path)
            if manifest and manifest.get("session"):
                pairs.append((Path(manifest["session"]), manifest_path.parent.name))
        if not pairs:
            return f"{out}: no sessions have been run here; give SESSION files"
    cache = Cache(out / CACHE_DIR)
    blocks = []
    for session, sid in pairs:
        manifest = read_manifest(out / sid / MANIFEST)
        spec, note = pipeline_for(manifest)
        states = stage_states(spec, session, manifest, cache, *_reader_now(session, spec, registry))
        blocks.append(render(session, spec, states, out / sid, note, (manifest or {}).get("error")))
    return "\n".join(blocks)


def _reader_now(
    session: Path, pipeline: Pipeline, registry: Registry
) -> tuple[dict | str | None, str | None]:
    """The reader that would read ``session`` now (or why none would), and the session's digest."""
    session = Path(session)
    if not session.is_file():
        return None, None
    try:
        reader = claimant(registry, session, pipeline.reader)
        return reader_identity(registry, reader, session), session_digest(session, reader)
    except ImupipeError as exc:
        return f"cannot be read: {exc}", session_digest(session)


__all__ = [
    "Job",
    "JobResult",
    "RegistrySpec",
    "batch",
    "expand_inputs",
    "process_session",
    "run_job",
    "run_sessions",
    "session_ids",
    "status",
    "summary",
]

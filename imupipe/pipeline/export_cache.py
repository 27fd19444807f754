"""Exported files (calibration.json, the report and its figures, the residual map) as cached artefacts.

An exporter's files depend only on the tables it is given and the run's context,
so they are keyed like a stage run: the sha256 of the exporter's name, ``version``
and plugin distribution, the content digests of its input tables and the context
(session, pipeline name, imupipe version, skipped stages, raw units, and what the
run's verdict is made from: every stage output's digest and the streams' facts). Then:

* the session folder's ``.exports.json`` records, per exporter, the key its files
  were made with and each file's size and mtime: when the key is the same and the
  files are untouched, nothing is done (a warm run redraws no figure);
* else, a cache entry ``<out>/.cache/exports/<key[:2]>/<key>/`` holding the files
  (``files.json`` written last) is copied into the session folder;
* else the exporter runs, and what it wrote is stored in a new entry.

Only exporters that list what they write (``writes``) are cached; the files
kept are the paths their ``export`` returns.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ..io import copy_file, remove, write_text
from .cache import canonical, sha256

MARKER = ".exports.json"
EXPORTS_DIR = "exports"
INDEX = "files.json"
CONTEXT_KEYS = ("session", "pipeline", "imupipe_version", "skipped", "raw_units", "verdict_inputs")


def export_key(name: str, exporter: Any, distribution: dict | None, digests: Mapping[str, str],
               context: Mapping[str, Any]) -> str:
    """The key of one exporter's files: what they are made from (``digests``: table -> digest)."""
    return sha256(canonical({
        "exporter": name,
        "version": str(getattr(exporter, "version", "")),
        "distribution": distribution,
        "tables": dict(sorted(digests.items())),
        "context": {k: context.get(k) for k in CONTEXT_KEYS},
    }))


def table_digests(refs: Any, stages: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
    """``str(ref) -> digest`` of the tables ``refs`` name that exist (``stages``: run.json's)."""
    out = {}
    for ref in refs:
        rec = stages.get(ref.source) or {}
        if rec.get("status") in ("ran", "cached") and ref.port in (rec.get("outputs") or {}):
            out[str(ref)] = rec["outputs"][ref.port]
    return out


def cacheable(exporter: Any) -> bool:
    return bool(getattr(exporter, "writes", ()))


def read_marker(run_dir: Path) -> dict:
    try:
        marker = json.loads((Path(run_dir) / MARKER).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}
    return marker if isinstance(marker, dict) else {}


def _stat(path: Path) -> list[int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def in_place(run_dir: Path, name: str, key: str) -> list[Path] | None:
    """The files of exporter ``name`` if the session folder holds them made with ``key``, untouched."""
    entry = read_marker(run_dir).get(name)
    if not isinstance(entry, dict) or entry.get("key") != key:
        return None
    files = entry.get("files") or {}
    paths = [Path(run_dir) / rel for rel in files]
    if any(_stat(p) != files[rel] for p, rel in zip(paths, files)):
        return None
    return paths


def _mark(run_dir: Path, name: str, key: str, paths: list[Path]) -> None:
    marker = read_marker(run_dir)
    marker[name] = {"key": key,
                    "files": {p.relative_to(run_dir).as_posix(): _stat(p) for p in paths}}
    write_text(Path(run_dir) / MARKER, json.dumps(marker, indent=1, sort_keys=True) + "\n")


def run_cached(name: str, exporter: Any, key: str, tables: Callable[[], Mapping[str, Any]],
               context: Callable[[], Mapping[str, Any]], run_dir: Path, cache_root: Path
               ) -> list[Path]:
    """Export through the cache; ``tables()`` and ``context()`` are called only when the
    exporter has to run."""
    run_dir = Path(run_dir)
    if not cacheable(exporter):
        return exporter.export(tables(), context(), run_dir)
    here = in_place(run_dir, name, key)
    if here is not None:
        return here
    entry = Path(cache_root) / EXPORTS_DIR / key[:2] / key
    try:
        stored = json.loads((entry / INDEX).read_text())["files"]
    except (FileNotFoundError, json.JSONDecodeError, KeyError, TypeError):
        stored = None
    if stored is not None and all((entry / rel).is_file() for rel in stored):
        for target in getattr(exporter, "writes", ()):  # exactly the cached set, nothing stale
            remove(run_dir / target)
        paths = [run_dir / rel for rel in stored]
        for rel, dst in zip(stored, paths):
            copy_file(entry / rel, dst)
        _mark(run_dir, name, key, paths)
        return paths
    written = [Path(p) for p in exporter.export(tables(), context(), run_dir)]
    inside = [p for p in written if p.resolve().is_relative_to(run_dir.resolve()) and p.is_file()]
    rels = [p.resolve().relative_to(run_dir.resolve()).as_posix() for p in inside]
    for rel, src in zip(rels, inside):
        copy_file(src, entry / rel)
    write_text(entry / INDEX, json.dumps({"key": key, "files": rels}, indent=1) + "\n")
    _mark(run_dir, name, key, [run_dir / r for r in rels])
    return written

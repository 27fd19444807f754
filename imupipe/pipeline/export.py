"""Calibrations in other software's formats: ``run --export F,...`` and ``imupipe export RUN_DIR``.

Files go to ``<out>/<session>/export/``, which always matches the session's
``calibration.json``: every run clears it before exporting (a stale file from an
earlier calibration never stays beside a new one). A format is any registered
exporter with ``target`` and ``files`` attributes (``imupipe.formats``).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
from pyarrow import ipc

from .. import __version__, schemas
from ..errors import ImupipeError
from ..formats._common import EXPORT_DIR, NOISE_SCHEMA, ExportError
from ..models import Calibration
from ..plugins import Registry
from .cache import Cache, read_manifest

CALIBRATION, MANIFEST, CACHE_DIR = "calibration.json", "run.json", ".cache"


def format_names(registry: Registry) -> list[str]:
    return [n for n in registry.names("exporters")
            if hasattr(registry.get("exporters", n), "target")]


def parse_formats(text: str | Sequence[str] | None, registry: Registry) -> tuple[str, ...]:
    """``"kalibr,px4"`` (or a list of such) -> checked names; unknown ones are an error."""
    if not text:
        return ()
    items = [text] if isinstance(text, str) else list(text)
    names = [n.strip() for item in items for n in item.split(",") if n.strip()]
    known = format_names(registry)
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ImupipeError(f"--export/--format: unknown format {', '.join(map(repr, unknown))}; "
                           f"known: {', '.join(known) or 'none'}")
    return tuple(dict.fromkeys(names))


def export_formats(formats: Sequence[str], results: Mapping[str, pa.Table],
                   context: Mapping[str, Any], run_dir: Path, registry: Registry) -> list[Path]:
    """Clear ``run_dir/export`` and write every format there, or (on an error) none."""
    out = Path(run_dir) / EXPORT_DIR
    _clear(out)
    written: list[Path] = []
    try:
        for name in formats:
            written += registry.get("exporters", name).export(results, context, out)
    except BaseException as exc:
        _clear(out)  # all the formats asked for, or none
        if isinstance(exc, ImupipeError) and not isinstance(exc, ExportError):
            raise ExportError(f"{name} export: {exc}") from None
        raise
    return written


def _clear(folder: Path) -> None:
    if folder.is_dir() and not folder.is_symlink():
        shutil.rmtree(folder)


def noise_tables(tables: Mapping[str, pa.Table]) -> dict[str, pa.Table]:
    return {k: t for k, t in tables.items() if schemas.schema_of(t) == NOISE_SCHEMA}


def export_run_dir(run_dir: Path, formats: Sequence[str], registry: Registry) -> list[Path]:
    """``imupipe export RUN_DIR``: the formats of a finished run's ``calibration.json``."""
    run_dir = Path(run_dir)
    cal_path = run_dir / CALIBRATION
    if not cal_path.is_file():
        raise ImupipeError(f"{run_dir}: no {CALIBRATION} here; give a session's folder of "
                           "`imupipe run --out DIR` (DIR/<session>), after a successful run")
    try:
        doc = json.loads(cal_path.read_text())
        calibration = Calibration.from_dict(doc)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ImupipeError(f"{cal_path}: not a readable calibration ({type(exc).__name__}: "
                           f"{exc}); rerun `imupipe run`") from None
    manifest = read_manifest(run_dir / MANIFEST) or {}
    raw_units = {s: doc[s]["raw_units"] for s in calibration.triads if "raw_units" in doc[s]}
    context = {
        "session": doc.get("session", manifest.get("session", str(run_dir))),
        "pipeline": doc.get("pipeline", "?"), "imupipe_version": __version__,
        "raw_units": raw_units or manifest.get("raw_units") or {},
        "stream_facts": manifest.get("stream_facts") or {}, "device": manifest.get("device"),
    }
    results = {"calibration": calibration.to_table(),
               **noise_tables(_cached_outputs(run_dir.parent / CACHE_DIR, manifest))}
    return export_formats(formats, results, context, run_dir, registry)


def _cached_outputs(cache_dir: Path, manifest: dict) -> dict[str, pa.Table]:
    """The run's cached stage outputs of schema ``noise`` (only their schemas are read first)."""
    cache, out = Cache(cache_dir), {}
    for key, record in (manifest.get("stages") or {}).items():
        if record.get("status") not in ("ran", "cached") or not record.get("key"):
            continue
        for port in record.get("outputs") or {}:
            path = cache_dir / record["key"][:2] / record["key"] / f"{port}.arrow"
            try:
                with pa.memory_map(str(path), "r") as f:
                    sid = (ipc.open_file(f).schema.metadata or {}).get(schemas.SCHEMA_KEY)
            except (OSError, pa.ArrowInvalid):
                continue
            if sid == NOISE_SCHEMA.encode():
                out[f"{key}.{port}"] = cache.load(record["key"], port)
    return out

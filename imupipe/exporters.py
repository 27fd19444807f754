"""Built-in exporters: ``calibration.json`` (``spec/contracts.md``).

An exporter receives the tables a pipeline's ``[export]`` section names (in
that order), a context (``session``, ``pipeline``, ``imupipe_version``, notes
such as skipped stages, and ``raw_units``: stream -> unit of raw values a reader
left unconverted, e.g. ``{"accel": "counts"}``) and an output directory, and
writes files there atomically. An exporter may list the names it writes under
the directory in ``writes`` (a failed rerun removes them).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa

from .errors import SolverError
from .hookspecs import hookimpl
from .io import write_text
from .models import SENSORS, UNITS, Calibration

CONTEXT_KEYS = ("session", "pipeline", "imupipe_version")


class CalibrationJson:
    """``out_dir/calibration.json``: the calibration tables merged, later tables win per sensor;
    with a ``diagnosis`` table among them, its accepted terms as ``model_terms``."""

    name = "calibration_json"
    version = "2"  # bump when the file changes for the same tables (keys the export cache)
    filename = "calibration.json"
    writes = (filename,)

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        from . import schemas

        diagnoses = [t for t in results.values() if schemas.schema_of(t) == "diagnosis"]
        tables = [t for t in results.values() if schemas.schema_of(t) != "diagnosis"]
        if not tables:
            raise SolverError(
                f"{context.get('session', '?')}: no calibration table to export "
                "(every calibrate stage was skipped); check the session's streams"
            )
        meta = {k: context[k] for k in CONTEXT_KEYS if k in context}
        if context.get("skipped"):
            meta["skipped_stages"] = dict(context["skipped"])
        calibration = Calibration.from_tables(*tables, meta=meta)
        if not calibration.triads:
            raise SolverError(
                f"{context.get('session', '?')}: the calibration tables hold no triad"
            )
        doc = with_raw_units(calibration.to_dict(), context.get("raw_units") or {})
        if context.get("verdict") is not None:  # spec/contracts.md; imupipe.verdict
            doc["verdict"] = dict(context["verdict"])
        for table in diagnoses:  # imupipe diagnose: the accepted extra terms (effects.md names)
            findings = json.loads(table.schema.metadata[b"imupipe.diagnosis"])["findings"]
            doc["model_terms"] = [{"effect": f["effect"], "sensor": f["sensor"], "parameters": f["parameters"]}
                                  for f in findings if f["effect"] != "unknown"]
        path = Path(out_dir) / self.filename
        write_text(path, json.dumps(doc, indent=2) + "\n")
        return [path]


def with_raw_units(doc: dict[str, Any], raw_units: Mapping[str, str]) -> dict[str, Any]:
    """Say per triad in which unit ``b0`` and ``k`` are (and ``M`` maps from): ``raw_units``.

    ``units`` is what ``M`` corrects to (SI); the raw unit is SI too unless the
    reader left the values unconverted (a manifest's ``unit = "counts"``).
    """
    for sensor in SENSORS:
        if sensor not in doc:
            continue
        raw, si = raw_units.get(sensor, UNITS[sensor]), UNITS[sensor]
        doc[sensor]["raw_units"] = raw
        if raw != si:
            doc[sensor]["raw_units_note"] = (
                f"b0 in {raw}, k in {raw}/degC; M maps {raw} to {si}"
            )
    if raw_units.get("temperature", "degC") != "degC":
        doc["temperature_raw_units"] = raw_units["temperature"]
    return doc


def _metadata_json(results: Mapping[str, pa.Table], schema: str, key: bytes, context: Mapping[str, Any],
                   path: Path) -> list[Path]:
    """``path`` from the JSON document a table of ``schema`` carries in its metadata ``key``,
    with the run's session; [] when no such table is among the results."""
    from . import schemas

    for table in results.values():
        if schemas.schema_of(table) == schema:
            doc = json.loads(table.schema.metadata[key])
            doc["session"] = str(context.get("session", doc.get("session", "")))
            write_text(path, json.dumps(doc, indent=1) + "\n")
            return [path]
    return []


class ResidualMapFiles:
    """``out_dir/residual_map.json`` and ``out_dir/residuals.parquet`` (``spec/contracts.md``): the
    map of where the model fails and the whitened per-sample residual table it was built from,
    from the tables of schemas ``residual_map`` and ``sample_residuals`` among the results."""

    name = "residual_map"
    version = "1"
    writes = ("residual_map.json", "residuals.parquet")

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        from . import schemas
        from .io import atomic_path

        written = _metadata_json(results, "residual_map", b"imupipe.residual_map", context,
                                 Path(out_dir) / "residual_map.json")
        for table in results.values():
            if schemas.schema_of(table) == "sample_residuals":
                import pyarrow.parquet as pq

                path = Path(out_dir) / "residuals.parquet"
                with atomic_path(path) as tmp:
                    # dictionaries for the text columns only: trying them on a million distinct
                    # floats was a fifth of the write, for a file 4 % larger (the 1 h session)
                    strings = [f.name for f in table.schema if pa.types.is_string(f.type)]
                    pq.write_table(table, tmp, compression="zstd", use_dictionary=strings)
                written.append(path)
        return written


class DiagnosisJson:
    """``out_dir/diagnosis.json`` (``spec/contracts.md``) from the table of schema ``diagnosis``."""

    name = "diagnosis"
    version = "2"
    writes = ("diagnosis.json",)

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        return _metadata_json(results, "diagnosis", b"imupipe.diagnosis", context,
                              Path(out_dir) / "diagnosis.json")


class NoiseJson:
    """``out_dir/noise.json``: the recording's own noise model (the ``estimate_noise`` stage), from
    the table of schema ``noise`` among the results: per triad and axis noise density, random
    walk, bias instability, quantisation, rate ramp, the per-sample white sigma and the sample
    rate; a ``kalibr`` block (largest axis, Kalibr's names and units); the rests used."""

    name = "noise_json"
    version = "2"
    writes = ("noise.json",)

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        return _metadata_json(results, "noise", b"imupipe.noise", context, Path(out_dir) / "noise.json")


COMPONENTS: list = [CalibrationJson(), ResidualMapFiles(), DiagnosisJson(), NoiseJson()]


@hookimpl
def imupipe_register_exporters(register):
    for exporter in COMPONENTS:
        register(exporter)

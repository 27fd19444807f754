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
    """``out_dir/calibration.json``: the calibration tables merged, later tables win per sensor."""

    name = "calibration_json"
    filename = "calibration.json"
    writes = (filename,)

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        if not results:
            raise SolverError(
                f"{context.get('session', '?')}: no calibration table to export "
                "(every calibrate stage was skipped); check the session's streams"
            )
        meta = {k: context[k] for k in CONTEXT_KEYS if k in context}
        if context.get("skipped"):
            meta["skipped_stages"] = dict(context["skipped"])
        calibration = Calibration.from_tables(*results.values(), meta=meta)
        if not calibration.triads:
            raise SolverError(
                f"{context.get('session', '?')}: the calibration tables hold no triad"
            )
        doc = with_raw_units(calibration.to_dict(), context.get("raw_units") or {})
        if context.get("verdict") is not None:  # spec/contracts.md; imupipe.verdict
            doc["verdict"] = dict(context["verdict"])
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


class ResidualMapFiles:
    """``out_dir/residual_map.json`` and ``out_dir/residuals.parquet`` (``spec/contracts.md``): the
    map of where the model fails and the whitened per-sample residual table it was built from,
    from the tables of schemas ``residual_map`` and ``sample_residuals`` among the results."""

    name = "residual_map"
    writes = ("residual_map.json", "residuals.parquet")

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        from . import schemas
        from .io import atomic_path

        written = []
        for table in results.values():
            sid = schemas.schema_of(table)
            if sid == "residual_map":
                doc = json.loads(table.schema.metadata[b"imupipe.residual_map"])
                doc["session"] = str(context.get("session", doc.get("session", "")))
                path = Path(out_dir) / "residual_map.json"
                write_text(path, json.dumps(doc, indent=1) + "\n")
                written.append(path)
            elif sid == "sample_residuals":
                import pyarrow.parquet as pq

                path = Path(out_dir) / "residuals.parquet"
                with atomic_path(path) as tmp:
                    pq.write_table(table, tmp, compression="zstd")
                written.append(path)
        return written


class DiagnosisJson:
    """``out_dir/diagnosis.json`` (``spec/contracts.md``) from the table of schema ``diagnosis``."""

    name = "diagnosis"
    writes = ("diagnosis.json",)

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        from . import schemas

        written = []
        for table in results.values():
            if schemas.schema_of(table) == "diagnosis":
                doc = json.loads(table.schema.metadata[b"imupipe.diagnosis"])
                doc["session"] = str(context.get("session", doc.get("session", "")))
                path = Path(out_dir) / "diagnosis.json"
                write_text(path, json.dumps(doc, indent=1) + "\n")
                written.append(path)
                written += self._terms_into_calibration(doc, Path(out_dir) / "calibration.json")
        return written

    @staticmethod
    def _terms_into_calibration(doc: dict, path: Path) -> list[Path]:
        """The accepted terms join ``calibration.json`` as ``model_terms`` (effects.md names)."""
        if not path.exists():
            return []
        cal = json.loads(path.read_text())
        cal["model_terms"] = [{"effect": f["effect"], "sensor": f["sensor"], "parameters": f["parameters"]}
                              for f in doc["findings"] if f["effect"] != "unknown"]
        write_text(path, json.dumps(cal, indent=1) + "\n")
        return [path]


class NoiseJson:
    """``out_dir/noise.json``: the recording's own noise model (the ``estimate_noise`` stage), from
    the table of schema ``noise`` among the results: per triad and axis noise density, random
    walk, bias instability, quantisation, rate ramp, the per-sample white sigma and the sample
    rate; a ``kalibr`` block (largest axis, Kalibr's names and units); the rests used."""

    name = "noise_json"
    writes = ("noise.json",)

    def export(
        self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path
    ) -> list[Path]:
        from . import schemas

        for table in results.values():
            if schemas.schema_of(table) == "noise":
                doc = {"session": str(context.get("session", "")),
                       **json.loads(table.schema.metadata[b"imupipe.noise"])}
                path = Path(out_dir) / "noise.json"
                write_text(path, json.dumps(doc, indent=1) + "\n")
                return [path]
        return []


COMPONENTS: list = [CalibrationJson(), ResidualMapFiles(), DiagnosisJson(), NoiseJson()]


@hookimpl
def imupipe_register_exporters(register):
    for exporter in COMPONENTS:
        register(exporter)

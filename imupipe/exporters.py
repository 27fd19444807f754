"""Built-in exporters: ``calibration.json`` (``spec/contracts.md``).

An exporter receives the tables a pipeline's ``[export]`` section names (in
that order), a context (``session``, ``pipeline``, ``imupipe_version`` and
notes such as skipped stages) and an output directory, and writes files there
atomically.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa

from .errors import SolverError
from .hookspecs import hookimpl
from .io import write_text
from .models import Calibration

CONTEXT_KEYS = ("session", "pipeline", "imupipe_version")


class CalibrationJson:
    """``out_dir/calibration.json``: the calibration tables merged, later tables win per sensor."""

    name = "calibration_json"
    filename = "calibration.json"

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
        path = Path(out_dir) / self.filename
        write_text(path, calibration.to_json())
        return [path]


COMPONENTS: list = [CalibrationJson()]


@hookimpl
def imupipe_register_exporters(register):
    for exporter in COMPONENTS:
        register(exporter)

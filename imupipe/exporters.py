"""Built-in exporters: ``calibration.json`` and friends."""

from __future__ import annotations

from .hookspecs import hookimpl

COMPONENTS: list = []


@hookimpl
def imupipe_register_exporters(register):
    for exporter in COMPONENTS:
        register(exporter)

"""Fixture plugin: just the built-in canonical CSV and MCAP readers (for batch workers)."""

from __future__ import annotations

from imupipe.hookspecs import hookimpl
from imupipe.readers import csv, mcap


@hookimpl
def imupipe_register_readers(register):
    for reader in (*csv.COMPONENTS, *mcap.COMPONENTS):
        register(reader)

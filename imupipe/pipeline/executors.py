"""Executors for batches: local process pool, Dask (extra ``imupipe[dask]``)."""

from __future__ import annotations

from ..hookspecs import hookimpl

COMPONENTS: list = []


@hookimpl
def imupipe_register_executors(register):
    for executor in COMPONENTS:
        register(executor)

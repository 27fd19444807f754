"""Every hook of imupipe: the plugin manual.

A plugin is a module (or object) with functions marked ``@hookimpl`` and named
after the specs below, published through the ``imupipe`` entry-point group::

    # pyproject.toml of a plugin distribution
    [project.entry-points.imupipe]
    my_reader = "my_package.reader_module"

Registration hooks receive a ``register`` callback; one module may register many
components. Names must be unique across all plugins: a duplicate is an error
naming both plugins.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pluggy

PROJECT = "imupipe"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

Register = Callable[[Any], None]


@hookspec
def imupipe_register_readers(register: Register) -> None:
    """Register ``Reader`` objects (``components.Reader``)."""


@hookspec
def imupipe_register_stages(register: Register) -> None:
    """Register ``Stage`` objects (``components.Stage``)."""


@hookspec
def imupipe_register_solvers(register: Register) -> None:
    """Register ``Solver`` objects (``components.Solver``)."""


@hookspec
def imupipe_register_exporters(register: Register) -> None:
    """Register ``Exporter`` objects (``components.Exporter``)."""


@hookspec
def imupipe_register_executors(register: Register) -> None:
    """Register ``Executor`` objects (``components.Executor``)."""


@hookspec
def imupipe_register_effects(register: Register) -> None:
    """Register omitted-physics ``Effect`` objects (``components.Effect``)."""


@hookspec(firstresult=True)
def imupipe_choose_reader(path: Path, head: bytes, readers: dict[str, Any]) -> str | None:
    """Name the reader for ``path`` (``head``: its first 64 bytes), or None to pass.

    The built-in implementation (``trylast``) asks every registered reader's
    ``sniff`` and fails when two claim the file; a plugin implementing this hook
    wins over it.
    """


@hookspec
def imupipe_before_stage(stage: str, key: str) -> None:
    """Observe: a stage is about to run (``key``: its cache key). Never change data."""


@hookspec
def imupipe_after_stage(stage: str, key: str, cached: bool, seconds: float) -> None:
    """Observe: a stage finished, or was taken from the cache."""

"""Progress on a terminal (rich); silent with ``--quiet`` or when output is not a terminal."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.progress import Progress


class _Silent:
    def add_task(self, *args, **kwargs) -> int:
        return 0

    def update(self, *args, **kwargs) -> None:
        pass

    def advance(self, *args, **kwargs) -> None:
        pass


@contextlib.contextmanager
def progress(quiet: bool = False) -> Iterator[Progress | _Silent]:
    """A progress display: ``task = p.add_task("what", total=n); p.advance(task)``."""
    if quiet or not sys.stderr.isatty():
        yield _Silent()
        return
    # imported here: a quiet run never loads rich
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, transient=True) as p:
        yield p

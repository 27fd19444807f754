"""Give the C heap's free pages back to the system between a run's phases.

glibc keeps the pages of freed arrays for later ``malloc`` calls. After the stages,
the report's figures allocate mostly Python objects (matplotlib's, in pymalloc's own
arenas), which cannot reuse them, so the process would grow past the stages' peak.
``malloc_trim(0)`` returns them first (a few milliseconds). A no-op where the C library
has no ``malloc_trim`` (macOS, Windows, musl).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def release_free_memory() -> None:
    """Return the C heap's free pages to the system (glibc), else nothing."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)

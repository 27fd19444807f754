"""How many BLAS threads imupipe's own linear algebra uses (``threadpoolctl``).

The solvers work on many small blocks (3x3 to ~60x60): a multi-threaded BLAS
only adds synchronisation there, and on a loaded machine (or with several batch
workers on the same cores) it oversubscribes them badly. So every imupipe
process, and every batch worker (local or Dask), runs its BLAS with
``DEFAULT_BLAS_THREADS`` thread unless told otherwise:

* ``--blas-threads N`` of ``imupipe run`` / ``imupipe batch`` (per process, per worker), or
* the environment variable ``IMUPIPE_BLAS_THREADS=N`` (also read by Dask workers
  started elsewhere). ``N`` is a positive integer. The option wins over the variable.

The results do not depend on the thread count beyond rounding.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from .errors import ConfigError

BLAS_THREADS_ENV = "IMUPIPE_BLAS_THREADS"
DEFAULT_BLAS_THREADS = 1


def blas_threads(option: int | None = None) -> int:
    """The BLAS thread count: ``option`` if given, else ``$IMUPIPE_BLAS_THREADS``, else 1."""
    if option is not None:
        if not isinstance(option, int) or isinstance(option, bool) or option < 1:
            raise ConfigError(f"--blas-threads {option!r}: expected a positive integer, e.g. 1")
        return option
    text = os.environ.get(BLAS_THREADS_ENV, "").strip()
    if not text:
        return DEFAULT_BLAS_THREADS
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise ConfigError(
            f"${BLAS_THREADS_ENV}={text!r}: expected a positive integer, e.g. 1; "
            "fix or unset the variable"
        )
    return value


def _load_blas() -> None:
    """Load every BLAS imupipe calls, so that the limit reaches them all.

    threadpoolctl limits the libraries already loaded: numpy and SciPy each ship
    their own OpenBLAS. SciPy's wheel keeps its own in ``scipy.libs``: that library is
    loaded by itself (2 ms), and ``scipy.linalg``, imported later, links to it, limited;
    importing ``scipy.linalg`` to load it would cost ~0.15 s that a pipeline without it
    (imu_tk's) never needs. Other installs load it with ``scipy.linalg``.
    """
    import numpy  # noqa: F401

    if "scipy.linalg" in sys.modules:
        return
    spec = importlib.util.find_spec("scipy")
    libs = Path(spec.origin).parent.parent / "scipy.libs" if spec and spec.origin else None
    found = sorted(libs.glob("libscipy_openblas*.so*")) if libs and libs.is_dir() else []
    if not found:
        import scipy.linalg  # noqa: F401
    for path in found:
        ctypes.CDLL(str(path))


@contextlib.contextmanager
def limited_blas(threads: int | None = None) -> Iterator[int]:
    """Run the block with ``blas_threads(threads)`` BLAS threads; restore the previous limits."""
    n = blas_threads(threads)
    import threadpoolctl

    _load_blas()
    with threadpoolctl.threadpool_limits(limits=n, user_api="blas"):
        yield n


def set_blas_threads(threads: int | None = None) -> int:
    """Limit this process's BLAS for good (a batch worker); returns the count set."""
    n = blas_threads(threads)
    import threadpoolctl

    _load_blas()
    threadpoolctl.threadpool_limits(limits=n, user_api="blas")
    return n


def blas_info() -> list[dict]:
    """threadpoolctl's view of the loaded BLAS libraries (``num_threads``, ``filepath``, ...)."""
    import threadpoolctl

    return [i for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]

"""Executors for batches: a local process pool, and Dask (extra ``imupipe[dask]``).

``map(fn, items, jobs, on_result=None)`` applies a module-level (picklable)
``fn`` to every item and returns the results in order; ``on_result(i, result)``
is called as each finishes (progress). ``fn`` is expected not to raise; if a
worker dies anyway, ``fn_failed(item, exc)`` of the batch turns it into a result.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable
from typing import Any

from ..errors import ImupipeError, require
from ..hookspecs import hookimpl

log = logging.getLogger("imupipe.pipeline")

OnResult = Callable[[int, Any], None] | None
SCHEDULER_ENV = "IMUPIPE_DASK_SCHEDULER"


def _default_jobs(jobs: int | None) -> int:
    return max(1, jobs if jobs else (os.cpu_count() or 1))


def _crashed(item: Any, exc: BaseException) -> Any:
    """The result a job that died in its worker stands for (the item names its failure)."""
    failed = getattr(item, "failed", None)
    if failed is None:
        raise exc
    return failed(f"worker died: {type(exc).__name__}: {exc}")


class LocalExecutor:
    """``concurrent.futures.ProcessPoolExecutor``; one job (or ``jobs=1``) runs inline."""

    name = "local"

    def map(
        self,
        fn: Callable[[Any], Any],
        items: list[Any],
        jobs: int | None,
        on_result: OnResult = None,
    ) -> list[Any]:
        jobs = min(_default_jobs(jobs), max(1, len(items)))
        results: list[Any] = [None] * len(items)
        if jobs == 1:
            for i, item in enumerate(items):
                results[i] = fn(item)
                if on_result:
                    on_result(i, results[i])
            return results
        import multiprocessing  # here: registering the executors is every command's (~7 ms)

        # spawn, not fork: a forked child of a process whose Arrow/Polars thread pools are
        # running can deadlock; spawned workers import ``fn`` by name instead
        context = multiprocessing.get_context("spawn")
        unfinished = _pool(fn, items, list(range(len(items))), jobs, results, on_result, context)
        for i in unfinished:  # a worker died: rerun the rest one per pool, so only the culprit fails
            _pool(fn, items, [i], 1, results, on_result, context, last_try=True)
        return results


def _pool(fn, items, indices, jobs, results, on_result, context, last_try=False) -> list[int]:
    """Run ``items[indices]`` in one process pool; return those cut short by a dead worker."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    broken = []
    with ProcessPoolExecutor(max_workers=min(jobs, len(indices)), mp_context=context) as pool:
        futures = {pool.submit(fn, items[i]): i for i in indices}
        for future in as_completed(futures):
            i = futures[future]
            try:
                results[i] = future.result()
            except BrokenProcessPool as exc:
                if not last_try:
                    broken.append(i)
                    continue
                results[i] = _crashed(items[i], exc)
            except Exception as exc:  # noqa: BLE001 - e.g. the job could not be pickled
                results[i] = _crashed(items[i], exc)
            if on_result:
                on_result(i, results[i])
    return sorted(broken)


class DaskExecutor:
    """``dask.distributed``: the scheduler at ``$IMUPIPE_DASK_SCHEDULER``, else a LocalCluster.

    The local cluster has ``jobs`` worker processes of one thread each and is
    closed when the batch ends. Its workers start without Dask's
    ``MALLOC_TRIM_THRESHOLD_=65536`` (returning freed memory to the OS that eagerly
    made the solvers' many temporary arrays page-fault again: 1.4-1.9x slower;
    a value the user exported is kept), nor the workers' statistical profiler and
    GIL monitor (for the dashboard, which a batch does not show), and they poll their event loop,
    the system and their memory less often. Dask's own log lines below warnings are
    not shown unless imupipe's logger is set to INFO or DEBUG.
    """

    name = "dask"

    def map(
        self,
        fn: Callable[[Any], Any],
        items: list[Any],
        jobs: int | None,
        on_result: OnResult = None,
    ) -> list[Any]:
        distributed = require("distributed", "dask")
        with _quiet_dask(), _dask_config():
            return self._map(distributed, fn, items, jobs, on_result)

    def _map(self, distributed, fn, items, jobs, on_result) -> list[Any]:
        address = os.environ.get(SCHEDULER_ENV)
        cluster = None
        if address:
            try:
                client = distributed.Client(address, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise ImupipeError(
                    f"cannot reach the Dask scheduler at {address!r} (${SCHEDULER_ENV}): {exc}; "
                    "start it, or unset the variable to use a local cluster"
                ) from None
        else:
            cluster = distributed.LocalCluster(
                n_workers=_default_jobs(jobs),
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
            )
            client = distributed.Client(cluster)
        try:
            futures = client.map(fn, items, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            results: list[Any] = [None] * len(items)
            for future in distributed.as_completed(futures):
                i = index[future.key]
                try:
                    results[i] = future.result()
                except Exception as exc:  # noqa: BLE001 - the worker died or could not unpickle
                    results[i] = _crashed(items[i], exc)
                if on_result:
                    on_result(i, results[i])
            return results
        finally:
            client.close()
            if cluster is not None:
                cluster.close()


@contextlib.contextmanager
def _dask_config():
    """Dask's defaults minus what slows imupipe's workers (see ``DaskExecutor``)."""
    import dask

    with dask.config.set({
        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
        # the workers' statistical profiler (a stack sample every 10 ms) and GIL monitor
        # are for Dask's dashboard, which a batch does not show
        "distributed.worker.profile.enabled": False,
        "distributed.admin.system-monitor.gil.enabled": False,
        # every server (scheduler, nannies, workers) polls its event loop's delay every 20 ms and
        # the system every 500 ms, and each memory manager checks every 100 ms; a batch of
        # minute-long jobs needs none of that so often (0.5 s CPU of a 4-session batch's 20)
        "distributed.admin.tick.interval": "1s",
        "distributed.admin.system-monitor.interval": "10s",
        "distributed.admin.system-monitor.disk": False,
        "distributed.worker.memory.monitor-interval": "1s",
    }):
        yield


@contextlib.contextmanager
def _quiet_dask():
    """Hide Dask's info lines (cluster start, worker registration) unless imupipe is verbose.

    Dask gives its loggers (``distributed.scheduler``, ...) levels of their own, so each
    is raised to WARNING for the batch, then restored.
    """
    if log.getEffectiveLevel() < logging.WARNING:
        yield
        return
    prefixes = ("distributed", "bokeh", "tornado")
    loggers = [logging.getLogger(p) for p in prefixes] + [
        lg for name, lg in logging.Logger.manager.loggerDict.items()
        if isinstance(lg, logging.Logger) and name.startswith(tuple(f"{p}." for p in prefixes))
    ]
    before = [(lg, lg.level) for lg in loggers]
    for lg in loggers:
        if lg.getEffectiveLevel() < logging.WARNING:
            lg.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for lg, level in before:
            lg.setLevel(level)


COMPONENTS: list = [LocalExecutor(), DaskExecutor()]


@hookimpl
def imupipe_register_executors(register):
    for executor in COMPONENTS:
        register(executor)

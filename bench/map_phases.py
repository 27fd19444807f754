"""The residual map's phases on a session: live memory peak and CPU of each, and the attitude integrations.

    python bench/map_phases.py SESSION [--pipeline default] [imupipe run arguments]

Runs ``imupipe run`` in this process (a fresh output folder, so nothing is cached) with
``tracemalloc`` on, and prints for each phase of the map stage (and the refine stage's fit)
the live memory before, at its peak and after (MiB of Python and numpy allocations:
``tracemalloc`` does not count the interpreter, the libraries' code or memory the allocator
keeps; ``bench/scaling.py`` gives the resident peak, ``bench/memory_timeline.py`` where it sits)
and its CPU seconds. The phases' peaks side by side say whether lowering one would lower the
run's: they sat within 2 % of each other at 1 h (issue 13). Phases nested in another (the
leverage inside the fit) are printed before it, and the outer peak counts them.

It also counts the attitude integrations (``Attitude.integrate``) and those whose rates equal
an earlier integration's on the same quadrature (a fit asking again for a point it evaluated),
with their CPU seconds. ``tracemalloc`` slows the run about 1.5x: compare runs of this script
with each other, not with ``bench/scaling.py``'s times.
"""

from __future__ import annotations

import functools
import hashlib
import sys
import tempfile
import time
import tracemalloc

import numpy as np

from imupipe.cli import main
from imupipe.diagnosis import attitude, evaluate, library, linearised, residual_map
from imupipe.solvers import blocktri
from imupipe.stages import residuals

MIB = 2**20
PHASES = [  # (object, attribute, label): the map's phases in the order they run
    (linearised, "solve_least_squares", "fit (Levenberg-Marquardt)"),
    (blocktri.Bordered, "leverage", "leverages"),
    (library, "structure_cells", "structure cells"),
    (evaluate, "sample_table", "per-sample table"),
    (residual_map, "model_rows", "model rows"),
    (residual_map, "rest_scatter_rows", "within-rest scatter rows"),
    (residual_map, "_cells_and_blocks", "cells of rows outside the fit"),
    (residuals, "magnetometer_rows", "magnetometer rows"),
]


def timed_phase(owner, name: str, label: str, lines: list) -> None:
    f = getattr(owner, name)

    @functools.wraps(f)
    def phase(*args, **kwargs):
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        t = time.process_time()
        out = f(*args, **kwargs)
        cpu = time.process_time() - t
        after, peak = tracemalloc.get_traced_memory()
        lines.append(f"{label:32s} {before / MIB:8.0f} {peak / MIB:8.0f} {after / MIB:8.0f} {cpu:8.2f}")
        return out

    setattr(owner, name, phase)


def counted_integrate(counts: dict) -> None:
    integrate = attitude.Attitude.integrate.__func__
    seen = set()

    def counted(cls, quad, omega):
        t = time.process_time()
        att = integrate(cls, quad, omega)
        cpu = time.process_time() - t
        key = (id(quad), hashlib.blake2b(np.ascontiguousarray(omega).data, digest_size=16).digest())
        repeat = key in seen
        seen.add(key)
        counts["calls"] += 1
        counts["cpu"] += cpu
        counts["repeats"] += repeat
        counts["repeat_cpu"] += cpu if repeat else 0.0
        return att

    attitude.Attitude.integrate = classmethod(counted)


def run() -> None:
    lines: list[str] = []
    for owner, name, label in PHASES:
        timed_phase(owner, name, label, lines)
    counts = {"calls": 0, "cpu": 0.0, "repeats": 0, "repeat_cpu": 0.0}
    counted_integrate(counts)
    tracemalloc.start()
    t = time.process_time()
    try:
        main(["run", "--quiet", "--out", tempfile.mkdtemp(), *sys.argv[1:]])
    except SystemExit as e:
        if e.code:
            raise
    total = time.process_time() - t
    print(f"{'phase (in the order they ended)':32s} {'before':>8s} {'peak':>8s} {'after':>8s} {'CPU s':>8s}"
          "   (live MiB, tracemalloc)")
    print("\n".join(lines))
    print(f"attitude integrations: {counts['calls']}, {counts['cpu']:.2f} s CPU; of them {counts['repeats']} "
          f"with rates already integrated, {counts['repeat_cpu']:.2f} s")
    print(f"whole run: {total:.1f} s CPU under tracemalloc")


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1].startswith("-"):
        sys.exit(__doc__)
    run()

"""Scaling benchmark: `imupipe run` on 0.5, 1, 2 and 4 h standard sessions beside `imupipe ingest`.

For each length, simulates a standard session (``imupipe simulate standard``, 100 Hz,
``n_positions`` chosen so the session lasts the given hours; seed 0) of the benches'
consumer-MEMS unit (``residual_nulls.realistic_imu``: gyro and accelerometer bias walks
the calibration detects at every length), then runs, each as a whole process as a user
runs it:

* ``imupipe ingest SESSION``: CPU (user + sys), wall, peak resident memory; the median of
  ``--ingest-runs`` (5) processes by CPU: a half-second process, one run of it varied by 20 %
  within an hour on a shared machine, and the run/ingest ratio with it;
* ``imupipe run SESSION`` (default pipeline, a fresh output directory so nothing is
  cached): CPU, wall, peak memory, and the slowest stages' wall seconds (run.json); the
  median of ``--runs`` (1) by CPU.

It prints one row per length with the run's sys time (the kernel's share of its CPU:
``perf`` shows it zeroing the fresh pages of large temporary arrays, ``clear_page_erms``),
the run/ingest CPU ratio and the peak memory beside the size of the decoded arrays (issue
13's target: <= 3x the arrays + 150 MiB), then the fitted log-log slope of run CPU, wall
and memory against hours (1.0 = linear) and the 4 h / 1 h CPU ratio (target <= 4.5), with
its user and sys parts apart, when both were run.

Each row names the bias walks of the residual map's null model (``walks``). They decide
the per-sample Jacobian's width: with both walks, every motion sample's row also carries
the walk states at the motion's two ends (16 entries instead of 4). ``--imu default`` (the
simulator's unit, no walk) is therefore not a fair scaling series: whether the map
estimates a tiny walk there depends on the session (measured: none at 1 h, both at 2 h,
and 8x the Jacobian's entries with them).

Peak memory is each child's own ``ru_maxrss`` (``os.wait4``); this script imports
nothing heavy itself, so the floor a forked child inherits stays small (printed).
BLAS runs with imupipe's default (one thread, ``imupipe/threads.py``). Wall clock
suffers when other processes share the cores; CPU is the steadier measure of work.

``--pipeline FILE`` runs another pipeline; ``--without-map`` runs the shipped ``calibrate``
one: the default without its residual map stage (the calibration's own cost).

Usage: ``python bench/scaling.py [--hours 0.5 1 2 4] [--imu realistic|default] [--keep DIR]
[--pipeline FILE | --without-map] [--runs 1] [--ingest-runs 5]``
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SIMULATE = r"""
import sys
import numpy as np
from imupipe.sim import protocols
from imupipe.sim.api import simulate

hours, out, imu = float(sys.argv[1]), sys.argv[2], sys.argv[3]
sys.path.insert(0, sys.argv[4])
from residual_nulls import realistic_imu

def duration(n):
    p = protocols.protocol_params("standard", n_positions=n)
    return protocols.build("standard", p, np.random.default_rng([0, 1])).trajectory.duration_s

# the session's length is affine in n_positions: two probes, then the n closest to the target
d1, d2 = duration(100), duration(1000)
n = max(10, round(100 + (hours * 3600 - d1) * 900 / (d2 - d1)))
simulate("standard", {}, 0, out, True, params={"n_positions": n},
         imu=realistic_imu(0) if imu == "realistic" else None)
"""

ARRAYS = r"""
import sys, pathlib, pyarrow as pa
total = 0
for p in pathlib.Path(sys.argv[1]).rglob("*.arrow"):
    with pa.memory_map(str(p)) as src:
        total += pa.ipc.open_file(src).read_all().nbytes
print(total)
"""

MIB = 1 << 20


def measure(cmd: list[str], **kw) -> dict:
    """Run ``cmd`` to completion: CPU (user + sys of the child) and its sys part, wall seconds, peak RSS bytes."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    out, err = proc.stdout.read(), proc.stderr.read()
    if proc.returncode:
        sys.exit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{err}")
    return {"cpu": usage.ru_utime + usage.ru_stime, "sys": usage.ru_stime, "wall": wall,
            "rss": usage.ru_maxrss * 1024, "stdout": out}


def median_of(runs: int, cmd: list[str], fresh: Path, **kw) -> dict:
    """The run of ``cmd`` with the median CPU of ``runs`` (each after ``fresh`` is removed)."""
    results = []
    for _ in range(runs):
        shutil.rmtree(fresh, ignore_errors=True)
        results.append(measure(cmd, **kw))
    return sorted(results, key=lambda r: r["cpu"])[len(results) // 2]


def null_walks(residual_map: Path) -> str:
    """The bias walks of the map's null model ("gyro+accel", "none"; "-" without a map)."""
    if not residual_map.exists():
        return "-"
    noise = json.loads(residual_map.read_text())["noise_model"]
    walks = [s for s in ("gyro", "accel") if any(noise.get(f"{s}_bias_walk_sigma", [0.0]))]
    return "+".join(walks) or "none"


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of log y against log x."""
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, nargs="+", default=[0.5, 1.0, 2.0, 4.0])
    ap.add_argument("--imu", choices=["realistic", "default"], default="realistic",
                    help="the simulated unit (default: the benches' realistic one, with bias walks)")
    ap.add_argument("--keep", type=Path, default=None, help="keep sessions and outputs here")
    ap.add_argument("--pipeline", type=Path, default=None, help="pipeline TOML (default: the built-in)")
    ap.add_argument("--without-map", action="store_true",
                    help="the calibrate pipeline: the default without its residual map stage")
    ap.add_argument("--runs", type=int, default=1, help="imupipe run processes per length (their median)")
    ap.add_argument("--ingest-runs", type=int, default=5, help="imupipe ingest processes per length (their median)")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="imupipe-scaling-"))
    work.mkdir(parents=True, exist_ok=True)
    pipeline = ["--pipeline", str(args.pipeline)] if args.pipeline else []
    if args.without_map:
        pipeline = ["--pipeline", "calibrate"]
    env = dict(os.environ)
    imupipe = [sys.executable, "-m", "imupipe"]
    rows = []
    try:
        for hours in sorted(args.hours):
            session = work / f"standard_{args.imu}_{hours:g}h.mcap"
            if not session.exists():
                measure([sys.executable, "-c", SIMULATE, str(hours), str(session), args.imu,
                         str(Path(__file__).resolve().parent)], env=env)
            truth = json.loads(Path(f"{session}.truth.json").read_text())
            n = truth["protocol_params"]["n_positions"]
            dur = truth["n_samples"] / truth["rate_hz"]
            tables = work / f"{session.stem}.tables"
            ingest = median_of(args.ingest_runs, [*imupipe, "ingest", str(session), "--out", str(tables)], tables,
                               env=env)
            arrays = int(measure([sys.executable, "-c", ARRAYS, str(tables)])["stdout"])
            out = work / f"out_{session.stem}"
            run = median_of(args.runs, [*imupipe, "run", str(session), "--out", str(out), "--quiet", *pipeline],
                            out, env=env)
            manifest = json.loads((out / session.stem / "run.json").read_text())
            stages = sorted(((v.get("seconds") or 0.0, k) for k, v in manifest["stages"].items()),
                            reverse=True)[:3]
            rows.append({"hours": hours, "n_positions": n, "duration_s": float(dur),
                         "ingest": ingest, "run": run, "arrays": arrays, "stages": stages,
                         "walks": null_walks(out / session.stem / "residual_map.json")})
            print(f"{hours:g} h done: run {run['cpu']:.1f} s CPU, ingest {ingest['cpu']:.2f} s CPU",
                  file=sys.stderr, flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)

    floor = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(f"imupipe run {' '.join(pipeline) or '(default pipeline)'} / ingest as whole processes, "
          "standard sessions at 100 Hz "
          f"of the {args.imu} unit, the median of {args.ingest_runs} ingest and {args.runs} run process(es) by CPU "
          f"(this script's own peak RSS, the floor of a child's: {floor / MIB:.0f} MiB)")
    print(f"{'hours':>5} {'n_pos':>5} {'min':>4} {'ingest CPU':>10} {'wall':>6} {'MiB':>5} | {'run CPU':>8} "
          f"{'sys':>5} {'wall':>7} {'peak MiB':>8} | {'run/ingest':>10} {'arrays MiB':>10} {'mem target':>10} | "
          f"{'walks':>10} | slowest stages (wall s)")
    for r in rows:
        i, u = r["ingest"], r["run"]
        target = 3 * r["arrays"] + 150 * MIB
        stages = ", ".join(f"{k} {s:.1f}" for s, k in r["stages"])
        print(f"{r['hours']:>5g} {r['n_positions']:>5} {r['duration_s'] / 60:>4.0f} {i['cpu']:>10.2f} {i['wall']:>6.2f} "
              f"{i['rss'] / MIB:>5.0f} | {u['cpu']:>8.1f} {u['sys']:>5.1f} {u['wall']:>7.1f} {u['rss'] / MIB:>8.0f} | "
              f"{u['cpu'] / i['cpu']:>9.1f}x {r['arrays'] / MIB:>10.1f} "
              f"{'ok' if u['rss'] <= target else 'OVER':>10} | {r['walks']:>10} | {stages}")
    if len(rows) >= 2:
        hours = [r["hours"] for r in rows]
        for what, key in (("CPU", "cpu"), ("wall", "wall"), ("peak memory", "rss")):
            print(f"log-log slope of run {what} against hours: "
                  f"{slope(hours, [r['run'][key] for r in rows]):.2f} (1.00 = linear)")
        print(f"log-log slope of ingest CPU against hours: "
              f"{slope(hours, [r['ingest']['cpu'] for r in rows]):.2f}")
    by = {r["hours"]: r for r in rows}
    if 1.0 in by and 4.0 in by:
        r4, r1 = by[4.0]["run"], by[1.0]["run"]
        print(f"run CPU 4 h / 1 h: {r4['cpu'] / r1['cpu']:.2f} (target <= 4.5); user time alone "
              f"{(r4['cpu'] - r4['sys']) / (r1['cpu'] - r1['sys']):.2f}, sys alone {r4['sys'] / r1['sys']:.2f}")
    if 1.0 in by:
        print(f"run / ingest CPU at 1 h: {by[1.0]['run']['cpu'] / by[1.0]['ingest']['cpu']:.1f}x "
              "(target <= 10x)")


if __name__ == "__main__":
    main()

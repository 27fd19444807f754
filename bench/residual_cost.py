"""Cost of the residual engine: forward model + noise model + map on a 30-minute 100 Hz session.

    python bench/residual_cost.py [--seed 0] [--repeat 3]

Simulates the standard protocol (about 30 min at 100 Hz), runs the default pipeline once to
fill the cache, then reruns only the ``map`` stage (a new ``--set map.fdr_q``, so the other
stages come from the cache) ``--repeat`` times and prints its CPU and wall seconds
beside the refine stage's and ``imupipe ingest`` of the same file, measured in the same run
(the machine is shared; the ratios are what carry over). Target: map <= 10 s on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from imupipe.sim.api import simulate


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed(cmd: list[str]) -> tuple[float, float]:
    c0, t0 = cpu(), time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return cpu() - c0, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="residual-cost-") as folder:  # ~0.5 GB: removed after
        measure(Path(folder), args.seed, args.repeat)


def measure(folder: Path, seed: int, repeat: int) -> None:
    session = folder / "standard.mcap"
    simulate("standard", {}, seed, session, quiet=True)
    out = folder / "out"
    exe = [sys.executable, "-m", "imupipe.cli"]
    timed([*exe, "run", str(session), "--out", str(out), "--quiet"])
    run = json.loads((out / "standard" / "run.json").read_text())
    refine_s = run["stages"]["refine"]["seconds"]
    samples = run["stream_facts"]["accel"]["samples"]
    rate = run["stream_facts"]["accel"]["rate_hz"]
    maps, ingests = [], []
    for k in range(repeat):
        fdr = f"map.fdr_q={0.05 + 1e-6 * (k + 1)}"  # a new value each time: only the map stage reruns
        c, w = timed([*exe, "run", str(session), "--set", fdr, "--out", str(out), "--quiet"])
        stage = json.loads((out / "standard" / "run.json").read_text())["stages"]["map"]
        maps.append((c, w, stage["seconds"]))
        ingests.append(timed([*exe, "ingest", str(session), "--out", str(folder / f"tables-{k}"), "--quiet"]))
    m = np.median(np.array(maps), axis=0)
    i = np.median(np.array(ingests), axis=0)
    print(f"session: {samples} samples per triad at {rate:g} Hz ({samples / rate / 60:.1f} min)")
    print(f"map stage wall {m[2]:.2f} s (whole process: {m[0]:.2f} s CPU, {m[1]:.2f} s wall); target <= 10 s")
    print(f"refine stage (first run) wall {refine_s:.2f} s; ingest process {i[0]:.2f} s CPU")
    print(f"ratios: map stage / ingest CPU {m[2] / i[0]:.2f}; map process / ingest process {m[0] / i[0]:.2f}")


if __name__ == "__main__":
    main()

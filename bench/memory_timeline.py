"""Where an imupipe command's memory peaks: its resident memory (RSS) along the run, with the code running then.

    python bench/memory_timeline.py run SESSION --out DIR [any imupipe arguments]
    python bench/memory_timeline.py --step 32 --top 8 run SESSION --out DIR

Runs the command in this process while a thread samples the resident set (``/proc/self/statm``,
Linux) every ``--every`` seconds with the innermost imupipe frames of the main thread. Prints
each change of at least ``--step`` MiB, then the ``--top`` highest phases (a phase ends where
RSS falls ``--step`` MiB below its highest sample), the peak first. Unlike
``tracemalloc``, this counts what the process holds: memory freed but kept by the allocators,
Arrow's buffers, file pages mapped and read. ``bench/scaling.py`` gives the peak; this says where
it is, and whether other phases sit just below it (then lowering the peak's phase alone moves
the peak by little).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import traceback

PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def resident_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 2**20


def where(frame, depth: int = 3) -> str:
    """The innermost ``depth`` imupipe frames of a stack, innermost first (file:line)."""
    own = [f for f in traceback.extract_stack(frame) if f"{os.sep}imupipe{os.sep}" in f.filename]
    return " < ".join(f"{os.path.basename(f.filename)}:{f.lineno}" for f in reversed(own[-depth:])) or "-"


class Sampler(threading.Thread):
    """Samples (seconds, RSS MiB, where) of the thread ``target`` until ``stop``."""

    def __init__(self, target: int, every: float):
        super().__init__(daemon=True)
        self.target, self.every, self.samples, self.done = target, every, [], threading.Event()
        self.t0 = time.perf_counter()

    def run(self) -> None:
        while not self.done.is_set():
            frame = sys._current_frames().get(self.target)
            self.samples.append((time.perf_counter() - self.t0, resident_mib(), where(frame) if frame else "-"))
            del frame  # held while waiting, it would keep the run's locals alive (a report's figures)
            self.done.wait(self.every)


def changes(samples: list, step: float) -> list:
    """The samples where RSS moved by at least ``step`` MiB since the last one kept."""
    out, last = [], -float("inf")
    for s in samples:
        if abs(s[1] - last) >= step:
            out.append(s)
            last = s[1]
    return out


def phases(samples: list, step: float, top: int) -> list:
    """The ``top`` highest phases, each its highest sample (seconds, MiB, where): a phase ends
    where RSS falls ``step`` MiB below its highest (the memory it held let go)."""
    out, high = [], None
    for s in samples:
        if high is not None and s[1] < high[1] - step:
            out.append(high)
            high = None
        if high is None or s[1] > high[1]:
            high = s
    if high is not None:
        out.append(high)
    return sorted(out, key=lambda s: -s[1])[:top]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=float, default=0.02, help="seconds between samples")
    ap.add_argument("--step", type=float, default=16.0, help="MiB of change printed in the timeline")
    ap.add_argument("--top", type=int, default=6, help="highest phases printed")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="imupipe's arguments")
    args = ap.parse_args(argv)
    if not args.command:
        ap.error("give an imupipe command, e.g. run SESSION --out DIR")
    if not os.path.exists("/proc/self/statm"):
        print("memory_timeline: needs Linux's /proc/self/statm", file=sys.stderr)
        return 2
    from imupipe.cli import main as imupipe

    sampler = Sampler(threading.get_ident(), args.every)
    sampler.start()
    try:
        status = imupipe(args.command)
    except SystemExit as exc:
        status = exc.code
    finally:
        sampler.done.set()
        sampler.join()
    samples = sampler.samples
    print(f"imupipe {' '.join(args.command)}: exit {status}; RSS every {args.every:g} s, "
          f"changes of {args.step:g} MiB or more")
    for t, mib, at in changes(samples, args.step):
        print(f"  {t:8.2f} s {mib:8.1f} MiB  {at}")
    print(f"highest phases (each ends where RSS falls {args.step:g} MiB below its top), peak first:")
    for t, mib, at in phases(samples, args.step, args.top):
        print(f"  {mib:8.1f} MiB at {t:8.2f} s  {at}")
    return int(status or 0)


if __name__ == "__main__":
    sys.exit(main())

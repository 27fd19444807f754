"""The map's change-point search: ruptures' PELT against imupipe's vectorised ``pelt_l2``.

    python bench/change_points.py [--rests 150 375 750 1550] [--repeat 3]

The residual map searches each sensor's rest-mean residual series for bias jumps with PELT
(``residual_map.change_points``). ruptures' ``Pelt`` loops in Python over candidate starts x
time; on a series without a change (a null session) PELT prunes no candidate, so that loop is
quadratic in the rests (10 s of a 4 h session's map, profiled). ``pelt_l2`` runs the same
recursion and pruning with each step vectorised over the candidates. For each series length
(a white 3-axis series as a 0.25 h to 4 h standard session has rests, without and with one mean
shift) it prints the best-of-``repeat`` seconds of each, their ratio, and whether the break
points agree.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import ruptures

from imupipe.diagnosis.residual_map import pelt_l2


def seconds(search, repeat: int) -> tuple[float, list[int]]:
    best, bkps = np.inf, []
    for _ in range(repeat):
        t = time.perf_counter()
        bkps = search()
        best = min(best, time.perf_counter() - t)
    return best, bkps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rests", type=int, nargs="+", default=[150, 375, 750, 1550])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"{'rests':>6s} {'series':>8s} {'ruptures s':>11s} {'pelt_l2 s':>10s} {'ratio':>7s}  same break points")
    for n in args.rests:
        for shift in (0.0, 0.5):
            z = np.random.default_rng(n).normal(size=(n, 3))
            z[n // 2:] += shift
            pen = 3 * 2 * np.log(n)  # as change_points
            ref, a = seconds(lambda: ruptures.Pelt(model="l2", min_size=3, jump=1).fit(z).predict(pen=pen)[:-1],
                             args.repeat)
            new, b = seconds(lambda: pelt_l2(z, pen), args.repeat)
            print(f"{n:6d} {'a step' if shift else 'null':>8s} {ref:11.3f} {new:10.3f} {ref / new:6.0f}x  {a == b}")


if __name__ == "__main__":
    main()

"""PELT's cost on a rest series: ``ruptures``' ``CostL2`` against imupipe's ``CumulativeL2``.

    python bench/change_points.py [--rests 375 750 1550] [--repeat 3]

The residual map searches each sensor's rest-mean residual series for bias jumps with PELT
(``residual_map.change_points``). ``CostL2`` sums a segment's squares anew for every candidate
segment, which made the search cubic in the rests (18 s of a 2 h session's map, profiled);
``CumulativeL2`` gives the same costs from cumulative sums. For each series length (a white
3-axis series with one mean shift, as a 0.5 h, 1 h, 2 h and 4 h standard session has rests), it
prints the best-of-``repeat`` seconds of each, their ratio, and whether the break points agree.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import ruptures

from imupipe.diagnosis.residual_map import CumulativeL2


def seconds(make, z: np.ndarray, pen: float, repeat: int) -> tuple[float, list[int]]:
    best, bkps = np.inf, []
    for _ in range(repeat):
        t = time.perf_counter()
        bkps = make().fit(z).predict(pen=pen)
        best = min(best, time.perf_counter() - t)
    return best, bkps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rests", type=int, nargs="+", default=[150, 375, 750, 1550])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"{'rests':>6s} {'CostL2 s':>9s} {'CumulativeL2 s':>15s} {'ratio':>6s}  same break points")
    for n in args.rests:
        z = np.random.default_rng(n).normal(size=(n, 3))
        z[n // 2:] += 0.5
        pen = 3 * 2 * np.log(n)  # as change_points
        ref, a = seconds(lambda: ruptures.Pelt(model="l2", min_size=3, jump=1), z, pen, args.repeat)
        new, b = seconds(lambda: ruptures.Pelt(custom_cost=CumulativeL2(), min_size=3, jump=1), z, pen, args.repeat)
        print(f"{n:6d} {ref:9.3f} {new:15.3f} {ref / new:5.1f}x  {a == b}")


if __name__ == "__main__":
    main()

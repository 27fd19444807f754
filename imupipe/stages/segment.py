"""Stillness segmentation: rests from the recording's own noise floor, turns between them.

Accel and gyro (the gyro on the accel's stamps) are low-passed by two box filters of
``lowpass_s`` and ``2/3 lowpass_s`` (zeros at 4, 6 and 8 Hz for 0.25 s), so a hand-held
hold trembling at 4-8 Hz still reads as a rest. A sample is a *core* sample when the
variance of both low-passed signals over a window centred on it (by time: irregular
stamps are fine) stays below a factor times the noise floor. The floor is measured over
an initial rest when ``initial_rest_s`` > 0; else a low quantile of the windowed variance
gives a first pass, and the floor is the median windowed variance inside the rests that
pass finds (the recording's own noise, vibration included). Each core run is then grown
back over the half window it lost: walking outward (from inside the core's last half
window, where tremor can hide a slow onset) over short (50 ms)
means of the raw signals, a triad whose whitened distance from the local rest mean
exceeds ``edge_sigma`` marks motion; the rest ends at that triad's last typical sample
(distance at most the median of a 3-dof chi) moved back twice the time the motion took
from there to be seen (slow onsets hide under the noise), and no later than the
low-passed signals allow. Holds that tremble (short means spreading twice as much as
white noise would, relative to the low-passed signals) take their edges from the
low-passed signals. Runs longer than ``min_rest_s`` become rests; gaps
longer than ``max_gap_s`` split them. The table ``stillness`` keeps what the segmentation
saw, for the report's figure and for the message when too few rests are found.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import schemas
from ..components import BoundSolver, Params, Stage
from ..errors import SolverError
from ..observations import Rests
from ..rotations import hold_intervals, quat_to_rotvec, ragged_turn_quaternions


EDGE_MEAN_S = 0.05  # s: the short mean of the raw signals that places the edges
CALM = 1.54  # median of a 3-dof chi: a sample as calm as a rest's typical one
VIBRATION_RATIO = 2.0  # holds tremble when short raw means spread this many times more than white
FIRST_PASS = 3.0  # the floor: median windowed variance below this times the noise_quantile
INITIAL_REST_MOVING = 0.1  # an "initial rest" that moves this fraction of its time is not one
ROWS = 1 << 16  # samples whose windowed statistics are formed at once (memory)


class SegmentParams(Params):
    """Units are in the names: ``window_s`` window of the variance test; ``lowpass_s`` box
    length of the vibration filter (0: none); ``min_rest_s`` shortest rest kept;
    ``max_gap_s`` a stamp gap that splits a rest; ``accel_threshold``, ``gyro_threshold``:
    factors on the noise floor (windowed variance); ``initial_rest_s``: seconds at the start
    known to be still (0: the floor from the recording's rests); ``noise_quantile``: the
    quantile of windowed variance taken as noise in the first pass; ``edge_sigma``: how far
    (in noise sigmas) a sample leaves the rest mean to end the rest (0: rest = core grown by
    nothing); ``trim_s``: dropped from both ends of each rest; ``min_rests``: fewer rests
    than this is an error that says what the segmentation saw."""

    window_s: float = Field(0.5, gt=0)
    lowpass_s: float = Field(0.25, ge=0)
    min_rest_s: float = Field(1.0, ge=0)
    max_gap_s: float = Field(0.5, gt=0)
    accel_threshold: float = Field(10.0, gt=0)
    gyro_threshold: float = Field(10.0, gt=0)
    initial_rest_s: float = Field(0.0, ge=0)
    noise_quantile: float = Field(0.1, ge=0, le=1)
    edge_sigma: float = Field(5.0, ge=0)
    trim_s: float = Field(0.0, ge=0)
    min_rests: int = Field(1, ge=1)


def xyz(table: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (k,) int64, values (k, 3)) of a sample table."""
    return table.column("t_ns").to_numpy(), np.column_stack(
        [table.column(c).to_numpy() for c in ("x", "y", "z")]).astype(float, copy=False)


def _window_sums(t_s: np.ndarray, window_s: float, values) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
    """``ROWS`` samples ``r`` at a time: ``(r, n, sums)``, each sample's count ``n`` and the sums
    of the rows ``values(i, j)`` (rows i..j-1 of a (k, d) array) over [t - w/2, t + w/2]: the
    differences of running sums formed over the chunk's windows alone, each chunk's continuing
    the one before from its partial sum (the very additions of one running sum over the whole
    recording, without one: a long recording's temporaries)."""
    k = len(t_s)
    prev = None  # (first index, running sums from it) of the chunk before
    for a in range(0, k, ROWS):
        r = slice(a, min(a + ROWS, k))
        lo = np.searchsorted(t_s, t_s[r] - window_s / 2, "left")
        hi = np.searchsorted(t_s, t_s[r] + window_s / 2, "right")
        first, last = int(lo[0]), int(hi[-1])  # first <= a <= the last index of the chunk before's
        x = values(first, last)
        c = np.empty((last - first + 1, *x.shape[1:]))
        if prev is None:
            c[0] = 0.0
            np.cumsum(x, axis=0, out=c[1:])
        else:
            c[0] = prev[1][first - prev[0]]
            c[1:] = x
            np.cumsum(c, axis=0, out=c)
        prev = (first, c)
        yield r, hi - lo, c[hi - first] - c[lo - first]


def box_mean(t_s: np.ndarray, v: np.ndarray, window_s: float) -> np.ndarray:
    """(k, 3) mean of ``v`` (k, 3) over [t - w/2, t + w/2] per sample (``v`` itself for w = 0)."""
    if window_s <= 0:
        return v
    out = np.empty(v.shape)
    for r, n, sums in _window_sums(t_s, window_s, lambda i, j: v[i:j] - v[0]):
        out[r] = sums / n[:, None] + v[0]
    return out


def lowpass(t_s: np.ndarray, v: np.ndarray, lowpass_s: float) -> np.ndarray:
    """(k, 3) ``v`` through boxes of ``lowpass_s`` and ``2/3 lowpass_s`` (zeros at 1/L, 1.5/L, 2/L Hz)."""
    return box_mean(t_s, box_mean(t_s, v, lowpass_s), 2 * lowpass_s / 3)


def windowed_variance(t_s: np.ndarray, v: np.ndarray, window_s: float, per_axis: bool = False) -> np.ndarray:
    """(k,) trace of the covariance of ``v`` (k, 3) over [t - w/2, t + w/2] per sample
    ((k, 3) the per-axis variances with ``per_axis``)."""
    median = np.median(v, axis=0)  # conditioning of the running sums

    def values(i: int, j: int) -> np.ndarray:
        x = v[i:j] - median
        return np.hstack([x, x * x])

    out = np.empty((len(t_s), 3) if per_axis else len(t_s))
    for r, n, sums in _window_sums(t_s, window_s, values):
        n = n.astype(float)
        s1, s2 = sums[:, :3], sums[:, 3:]
        var = np.maximum((s2 - s1 * s1 / n[:, None]) / np.maximum(n - 1, 1)[:, None], 0)
        var[n < 3] = np.inf  # too few samples to call it still
        out[r] = var if per_axis else var.sum(axis=1)
    return out


def runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive index ranges of the True runs of ``flag``."""
    edges = np.diff(np.concatenate([[0], flag.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), (np.flatnonzero(edges == -1) - 1).tolist(), strict=True))


def _floor(var: np.ndarray, sel: np.ndarray, what: str) -> float:
    v = var[sel & np.isfinite(var)]
    level = float(np.median(v)) if len(v) else np.nan
    if not np.isfinite(level) or level <= 0:
        raise SolverError(f"segmentation: cannot estimate the {what} noise floor (constant or empty signal, "
                          "or no still interval); give initial_rest_s over a true rest")
    return level


def _edge(dev: np.ndarray, start: int, stop: int, step: int, z: float,
          adaptive_calm: bool = False) -> tuple[int, int]:
    """Walking from ``start`` to ``stop`` (exclusive) by ``step`` over ``dev`` (k, c), each
    channel a whitened distance: (the edge, the first index beyond ``z``). The edge: the last
    index where the channel that first goes beyond ``z`` was calm (``CALM``; with
    ``adaptive_calm``, or the walk's median before it when larger: tremor), moved back twice
    as many samples as it took from there to beyond ``z``; both ``stop - step`` when no
    channel goes beyond ``z``."""
    idx = np.arange(start, stop, step)
    if not len(idx):
        return start - step, start - step
    over = dev[idx] > z
    beyond = np.flatnonzero(over.any(axis=1))
    if not len(beyond):
        return int(idx[-1]), int(idx[-1])
    k = beyond[0]
    channel = int(np.argmax(dev[idx[k]]))
    before = dev[idx[:k], channel]
    # calm: as close as a typical rest sample (correlated tremor residue sits above a white chi)
    calm = np.flatnonzero(before <= max(CALM, float(np.median(before)) if k and adaptive_calm else CALM))
    if not len(calm):
        return start - step, int(idx[k])
    # a slow (min-jerk) onset stays under the noise for a while before it is seen: measured on
    # simulated holds, twice the calm-to-seen time keeps 95 % of the rests within 50 ms of
    # the true ones (bench/segmentation.py)
    j = max(calm[-1] - 2 * (k - calm[-1]), 0)
    return int(idx[j]) if j > 0 else start - step, int(idx[k])


class Detection:
    """What the segmentation saw: core runs, grown runs, floors and thresholds (see module doc)."""

    def __init__(self, t_s: np.ndarray, a: np.ndarray, w: np.ndarray, p: SegmentParams):
        self.t_s, self.p = t_s, p
        breaks = np.flatnonzero(np.diff(t_s) > p.max_gap_s) + 1
        self.segment_id = np.zeros(len(t_s), np.int64)
        self.segment_id[breaks] = 1
        self.segment_id = np.cumsum(self.segment_id)
        la, lw = self._lowpass(a), self._lowpass(w)
        va, vw = self._variance(la), self._variance(lw)
        if p.initial_rest_s > 0:
            sel = t_s <= t_s[0] + p.initial_rest_s
            self.floor = {"accel": _floor(va, sel, "accelerometer"), "gyro": _floor(vw, sel, "gyroscope")}
            self._check_initial_rest(va, vw)
        else:
            first = {k: float(np.quantile(v[np.isfinite(v)], p.noise_quantile)) if np.isfinite(v).any() else np.nan
                     for k, v in (("accel", va), ("gyro", vw))}
            # clearly quiet windows only: slow motion must not raise the floor it is judged by
            sel = (va < FIRST_PASS * first["accel"]) & (vw < FIRST_PASS * first["gyro"])
            self.floor = {"accel": _floor(va, sel, "accelerometer"), "gyro": _floor(vw, sel, "gyroscope")}
        self.threshold = {"accel": p.accel_threshold * self.floor["accel"],
                          "gyro": p.gyro_threshold * self.floor["gyro"]}
        self.stat = {"accel": va / self.threshold["accel"], "gyro": vw / self.threshold["gyro"]}
        del va, vw, sel  # a long recording's arrays: the edge statistics below come on top
        core = (self.stat["accel"] < 1) & (self.stat["gyro"] < 1)
        core[breaks] = False
        self.cores = [r for r in runs(core) if self.segment_id[r[0]] == self.segment_id[r[1]]]
        # per-axis sigma inside the cores of the low-passed signals and of short means of the
        # raw ones: the units of the edge tests
        sa, sw = box_mean(t_s, a, EDGE_MEAN_S), box_mean(t_s, w, EDGE_MEAN_S)
        self.sigma = {key: self._core_sigma(x) for key, x in
                      (("accel", la), ("gyro", lw), ("accel_raw", sa), ("gyro_raw", sw))}
        # holds that tremble (4-8 Hz, hand-held) put their edges on the low-passed signals
        white_ratio = 1.0  # the two filters' spread ratio on white noise (still, unfiltered: 1)
        if p.lowpass_s > 0:
            white = np.random.default_rng(0).standard_normal((min(len(t_s), 4000), 3))
            tw = t_s[: len(white)]
            white_ratio = np.median(box_mean(tw, white, EDGE_MEAN_S).std(axis=0)
                                    / lowpass(tw, white, p.lowpass_s).std(axis=0))
        ratio = {s: float(np.median(self.sigma[s + "_raw"] / self.sigma[s])) for s in ("accel", "gyro")}
        self.vibrating = bool(p.lowpass_s > 0 and max(ratio.values()) > VIBRATION_RATIO * white_ratio)
        self.vibration_ratio = {s: r / white_ratio for s, r in ratio.items()}
        self.holds = [self._grow(i0, i1, (la, lw), (sa, sw)) for i0, i1 in self.cores]

    def _check_initial_rest(self, va: np.ndarray, vw: np.ndarray) -> None:
        """The pipeline says the first ``initial_rest_s`` are still: refuse when a tenth of it or
        more moves (windowed variance above the threshold over the recording's quietest
        windows), instead of taking motion for the noise floor."""
        p = self.p
        sel = (self.t_s <= self.t_s[0] + p.initial_rest_s) & np.isfinite(va) & np.isfinite(vw)
        moving = np.zeros(int(sel.sum()), bool)
        for v, factor in ((va, p.accel_threshold), (vw, p.gyro_threshold)):
            quiet = float(np.quantile(v[np.isfinite(v)], p.noise_quantile))
            moving |= v[sel] > factor * quiet
        if moving.mean() > INITIAL_REST_MOVING:
            first = float(self.t_s[np.flatnonzero(sel)[np.argmax(moving)]] - self.t_s[0])
            raise SolverError(
                f"segmentation: initial_rest_s = {p.initial_rest_s:g} s, but the first "
                f"{p.initial_rest_s:g} s are not still: {100 * moving.mean():.0f} % of it moves (from "
                f"{first:.1f} s); set initial_rest_s = 0 (floor from the recording's own rests) or "
                "to the length of the true initial rest")

    def _core_sigma(self, x: np.ndarray, chunk_s: float = 2.0) -> np.ndarray:
        """(3,) sd of ``x`` (k, 3) about its mean, per axis: the median over pieces of the
        cores (``chunk_s`` long, so slow drift stays out) of the pieces' sd."""
        t, sds = self.t_s, []
        for i0, i1 in self.cores:
            edges = np.searchsorted(t, np.arange(t[i0], t[i1] + 1e-9, chunk_s))
            for a, b in zip(edges, [*edges[1:], i1 + 1], strict=True):
                if b - a >= 5 and t[b - 1] - t[a] >= min(chunk_s, 2 * self.p.window_s) * 0.5:
                    sds.append(x[a:b].std(axis=0))
        if not sds:
            return np.full(3, np.inf)
        return np.maximum(np.median(np.array(sds), axis=0), 1e-300)

    def _lowpass(self, v: np.ndarray) -> np.ndarray:
        return lowpass(self.t_s, v, self.p.lowpass_s)

    def _variance(self, v: np.ndarray, per_axis: bool = False) -> np.ndarray:
        return windowed_variance(self.t_s, v, self.p.window_s, per_axis)

    def _grow(self, i0: int, i1: int, lp: tuple, raw: tuple) -> tuple[int, int]:
        """The core run [i0, i1] grown outward to the rest's edges, within its gap-free segment
        and the half window plus the filter's half span. Each edge is found on short raw means
        (sharp) and on the low-passed signals (early by at most the filter's half span ``h``,
        blind to 4-8 Hz tremor); the raw edge is kept unless it lies more than ``h`` beyond
        the low-passed one (vibrating holds)."""
        p, t = self.p, self.t_s
        if p.edge_sigma <= 0:
            return i0, i1
        h = 5 * p.lowpass_s / 6
        reach = p.window_s / 2 + h
        sid = self.segment_id  # non-decreasing: the core's gap-free segment by bisection
        seg0 = int(np.searchsorted(sid, sid[i0], "left"))
        seg1 = int(np.searchsorted(sid, sid[i0], "right")) - 1
        lo_lim = max(int(np.searchsorted(t, t[i0] - reach, "left")), seg0)
        hi_lim = min(int(np.searchsorted(t, t[i1] + reach, "right")) - 1, seg1)
        ends = []
        # the core's own last `reach` is walked again: under tremor a slow onset hides in it
        mid = (i0 + i1) // 2
        a0 = min(max(int(np.searchsorted(t, t[i0] + reach, "right")) - 1, i0), mid)
        a1 = max(min(int(np.searchsorted(t, t[i1] - reach, "left")), i1), mid)
        for edge, lo, hi, step in ((a0, lo_lim, a0, -1), (a1, a1, hi_lim, 1)):
            near = (slice(max(i0, int(np.searchsorted(t, t[a1] - p.window_s))), a1 + 1) if step > 0 else
                    slice(a0, min(i1, int(np.searchsorted(t, t[a0] + p.window_s))) + 1))
            rng = slice(lo, hi + 1)
            found = []
            for signals, suffix in ((lp, ""), (raw, "_raw")):
                dev = np.zeros((hi + 1 - lo, 2))  # the walk's own span, indexed from lo (not the recording)
                for j, (x, s) in enumerate(zip(signals, ("accel", "gyro"), strict=True)):
                    dev[:, j] = np.linalg.norm((x[rng] - x[near].mean(axis=0)) / self.sigma[s + suffix], axis=1)
                e_i, x_i = _edge(dev, edge - lo, (-1 if step < 0 else hi + 1 - lo), step, p.edge_sigma,
                                 adaptive_calm=self.vibrating)
                found.append((e_i + lo, x_i + lo))
            (e_lp, x_lp), (e_raw, _) = found
            if self.vibrating:
                ends.append(e_lp)
                continue
            # motion first seen in the low-passed signal at x_lp began at most h later
            if step > 0:
                cap = int(np.searchsorted(t, t[min(x_lp, len(t) - 1)] + h, "right")) - 1
                ends.append(min(e_raw, cap))
            else:
                cap = int(np.searchsorted(t, t[max(x_lp, 0)] - h, "left"))
                ends.append(max(e_raw, cap))
        lo_end, hi_end = min(ends[0], a0), max(ends[1], a1)
        return (lo_end, hi_end) if self.vibrating else (min(lo_end, i0), max(hi_end, i1))

    def rests(self) -> list[tuple[int, int]]:
        """Index ranges [i0, i1] (inclusive) of the holds, trimmed, at least ``min_rest_s`` long,
        overlapping neighbours cut at the middle of their overlap."""
        t, p = self.t_s, self.p
        holds = sorted(self.holds)
        out: list[tuple[int, int]] = []
        sid = self.segment_id
        for i0, i1 in holds:
            # grown into each other (no motion seen between), unless a gap parts them
            if out and i0 <= out[-1][1] + 1 and sid[i0] == sid[out[-1][1]]:
                out[-1] = (out[-1][0], max(out[-1][1], i1))
            else:
                out.append((i0, i1))
        kept = []
        for i0, i1 in out:
            if p.trim_s:
                i0 = int(np.searchsorted(t, t[i0] + p.trim_s))
                i1 = int(np.searchsorted(t, t[i1] - p.trim_s, "right")) - 1
            if i1 > i0 and t[i1] - t[i0] >= p.min_rest_s:
                kept.append((int(i0), int(i1)))
        return kept

    def hold_lengths(self) -> np.ndarray:
        return np.array([self.t_s[b] - self.t_s[a] for a, b in self.holds])

    def summary(self, n_rests: int) -> dict:
        lengths = self.hold_lengths()
        still = np.zeros(len(self.t_s), bool)
        for a, b in self.holds:
            still[a:b + 1] = True
        return {
            "rests": n_rests, "candidate_holds": len(lengths),
            "hold_s_min": float(lengths.min()) if len(lengths) else None,
            "hold_s_median": float(np.median(lengths)) if len(lengths) else None,
            "hold_s_max": float(lengths.max()) if len(lengths) else None,
            "holds_shorter_than_min_rest_s": int((lengths < self.p.min_rest_s).sum()),
            "still_fraction": float(still.mean()),
            "still_fraction_accel": float(np.mean(self.stat["accel"] < 1)),
            "still_fraction_gyro": float(np.mean(self.stat["gyro"] < 1)),
            "noise_floor": self.floor, "threshold": self.threshold,
            "floor_from": "initial_rest_s" if self.p.initial_rest_s > 0 else "rests",
            "vibrating": self.vibrating, "vibration_ratio": self.vibration_ratio,
            "params": self.p.model_dump(),
        }

    def table(self, a: np.ndarray, w: np.ndarray, t0: int, max_rows: int = 20000) -> pa.Table:
        """The ``stillness`` table: decimated signals, normalised statistics, hold flags."""
        still = np.zeros(len(self.t_s), bool)
        for i0, i1 in self.rests():
            still[i0:i1 + 1] = True
        k = slice(None, None, max(1, -(-len(self.t_s) // max_rows)))
        cols = {"t_s": self.t_s[k]}
        for name, v in (("accel", a), ("gyro", w)):
            for i, c in enumerate("xyz"):
                cols[f"{name}_{c}"] = v[k, i]
        cols |= {"accel_stat": self.stat["accel"][k], "gyro_stat": self.stat["gyro"][k], "rest": still[k]}
        summary = self.summary(len(self.rests()))
        return schemas.stamp(pa.table(cols), "stillness", {"imupipe.t0_ns": str(t0),
                                                           "imupipe.segmentation": json.dumps(summary)})


def too_few_message(det: Detection, n: int, needed: int) -> str:
    """One paragraph: what the segmentation saw and which parameter to change."""
    p, s = det.p, det.summary(n)
    saw = (f"segmentation: {n} rest(s) found, {needed} needed (min_rests); it saw {s['candidate_holds']} "
           f"candidate hold(s)")
    if s["candidate_holds"]:
        saw += (f" of {s['hold_s_min']:.2f}-{s['hold_s_max']:.2f} s (median {s['hold_s_median']:.2f} s), "
                f"{s['holds_shorter_than_min_rest_s']} shorter than min_rest_s = {p.min_rest_s:g} s")
    saw += (f"; still {100 * s['still_fraction']:.0f} % of the time; thresholds: windowed variance "
            f"(window_s = {p.window_s:g} s) below accel_threshold = {p.accel_threshold:g} x "
            f"{det.floor['accel']:.3g} (m/s^2)^2 and gyro_threshold = {p.gyro_threshold:g} x "
            f"{det.floor['gyro']:.3g} (rad/s)^2 (noise floor from {s['floor_from']})")
    lengths = np.sort(det.hold_lengths())[::-1]
    qa, qg = det.stat["accel"] < 1, det.stat["gyro"] < 1
    g_given_a = float(qg[qa].mean()) if qa.any() else 1.0  # the gyro still where the accel is
    a_given_g = float(qa[qg].mean()) if qg.any() else 1.0
    saw += (f"; where the accel is still the gyro is too {100 * g_given_a:.0f} % of the time, and the "
            f"accel where the gyro is {100 * a_given_g:.0f} %")
    shaky = ("gyro" if g_given_a < 0.8 and g_given_a < a_given_g else
             "accel" if a_given_g < 0.8 and a_given_g < g_given_a else None)
    if len(lengths) >= needed and s["holds_shorter_than_min_rest_s"] and lengths[needed - 1] >= 0.5:
        fix = f"lower min_rest_s to {lengths[needed - 1] * 0.95:.2f}"
    elif s["candidate_holds"] <= 2 and s["still_fraction"] > 0.9:
        fix = ("the recording is one long rest (static): for its noise model run it with the noise "
               "pipeline (--pipeline pipelines/noise.toml); to calibrate, record positions joined by turns")
    elif shaky:
        other = "accel" if shaky == "gyro" else "gyro"
        sel = (det.stat[other] < 1) & (det.stat[shaky] >= 1)
        level = float(np.quantile(det.stat[shaky][sel], 0.9))
        factor = getattr(p, f"{shaky}_threshold")
        fix = (f"the {shaky} moves where the {other} is still (there its variance reaches {level:.3g} x its "
               f"threshold, 90th percentile): if its holds are noisy or vibrating, raise {shaky}_threshold "
               f"to about {factor * 1.5 * level:.3g}; else check the {shaky} stream")
    elif s["still_fraction"] < 0.05:
        fix = ("raise accel_threshold and gyro_threshold (holds that vibrate or drift), or record holds "
               "of at least 1.5 s")
    else:
        fix = ("raise accel_threshold/gyro_threshold or lower window_s if the holds are there but broken "
               "up; else record more positions")
    return f"{saw}. Fix: {fix} (--set STAGE.PARAM=VALUE or the pipeline's params)"


def rest_stats(table: pa.Table, bounds_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (n, 3), one-sample covariance (n, 3, 3) and count (n,) within each [start, end] ns."""
    t, v = xyz(table)
    n = len(bounds_ns)
    mean, cov, count = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan), np.zeros(n, np.int64)
    for i, (a, b) in enumerate(bounds_ns):
        i0, i1 = np.searchsorted(t, a, "left"), np.searchsorted(t, b, "right")
        seg = v[i0:i1]
        count[i] = len(seg)
        if len(seg):
            mean[i] = seg.mean(axis=0)
        if len(seg) > 1:
            cov[i] = np.cov(seg.T)
    return mean, cov, count


def segment(inputs: Mapping[str, pa.Table], params: SegmentParams, solver: BoundSolver | None) -> dict:
    t_a, a = xyz(inputs["accel"])
    t_g = inputs["gyro"].column("t_ns").to_numpy()
    if len(t_a) < 10 or len(t_g) < 10:
        raise SolverError("segmentation: accel and gyro need at least 10 samples each")
    t0 = int(min(t_a[0], t_g[0]))
    ta_s, tg_s = (t_a - t0) * 1e-9, (t_g - t0) * 1e-9
    # from the gyro's columns: its (k, 3) copy is formed for the turns, after the detection's peak
    w_at_a = np.column_stack([np.interp(ta_s, tg_s, inputs["gyro"].column(c).to_numpy())
                              for c in ("x", "y", "z")])
    del tg_s
    det = Detection(ta_s, a, w_at_a, params)
    runs_ = det.rests()
    if len(runs_) < params.min_rests:
        raise SolverError(too_few_message(det, len(runs_), params.min_rests))
    bounds = np.array([[t_a[i0], t_a[i1]] for i0, i1 in runs_], dtype=np.int64)
    mean, cov, counts = {}, {}, {}
    for s in ("accel", "gyro", "mag"):
        if s in inputs:
            mean[s], cov[s], counts[s] = rest_stats(inputs[s], bounds)
    if "temperature" in inputs:
        tt = inputs["temperature"].column("t_ns").to_numpy()
        TT = inputs["temperature"].column("temperature").to_numpy()
        j0, j1 = np.searchsorted(tt, bounds[:, 0], "left"), np.searchsorted(tt, bounds[:, 1], "right")
        temp = np.array([TT[a:b].mean() if b > a else np.interp(0.5 * (a0 + b0), tt, TT)
                         for a, b, a0, b0 in zip(j0, j1, bounds[:, 0], bounds[:, 1], strict=True)])
    else:
        temp = np.full(len(bounds), np.nan)
    rests = Rests((bounds[:, 0] - t0) * 1e-9, (bounds[:, 1] - t0) * 1e-9, counts["accel"], mean, cov,
                  temp, counts, t0)
    table = rests.to_table()
    meta = dict(table.schema.metadata or {})
    meta[b"imupipe.segmentation"] = json.dumps(det.summary(len(rests))).encode()
    return {"rests": table.replace_schema_metadata(meta), "turns": turns_table(rests, *xyz(inputs["gyro"]), t0),
            "stillness": det.table(a, w_at_a, t0)}


def turns_table(rests: Rests, t_g: np.ndarray, w: np.ndarray, t0: int) -> pa.Table:
    """The motion between each pair of consecutive rests, with its raw (bias-removed) angle."""
    m = len(rests) - 1
    starts = t0 + np.round(rests.t_end_s[:-1] * 1e9).astype(np.int64)
    ends = t0 + np.round(rests.t_start_s[1:] * 1e9).astype(np.int64)
    ts, ws = [], []
    for j in range(m):
        i0, i1 = np.searchsorted(t_g, starts[j], "left"), np.searchsorted(t_g, ends[j], "right")
        bias = 0.5 * (rests.mean["gyro"][j] + rests.mean["gyro"][j + 1])
        ts.append((t_g[i0:i1] - t0) * 1e-9)
        ws.append(w[i0:i1] - bias)
    angles = np.degrees(np.linalg.norm(quat_to_rotvec(ragged_turn_quaternions(
        ts, ws, hold_intervals)), axis=1)) if m > 0 else np.zeros(0)
    table = pa.table({
        "index": np.arange(m, dtype=np.int64), "rest_before": np.arange(m, dtype=np.int64),
        "rest_after": np.arange(1, m + 1, dtype=np.int64), "t_start_ns": starts, "t_end_ns": ends,
        "duration_s": (ends - starts) * 1e-9, "n_samples": np.array([len(t) for t in ts], np.int64),
        "angle_deg": angles,
    })
    return schemas.stamp(table, "turns", {"imupipe.t0_ns": str(t0)})


STAGE = Stage(
    name="segment_stillness", version="4", func=segment,
    inputs={"accel": "accel", "gyro": "gyro", "mag": "mag", "temperature": "temperature"},
    outputs={"rests": "rests", "turns": "turns", "stillness": "stillness"}, params=SegmentParams,
    optional_inputs=frozenset({"mag", "temperature"}),
    description="rests from low-passed accel and gyro variance against the recording's noise floor; "
                "turns between consecutive rests",
)
COMPONENTS = [STAGE]

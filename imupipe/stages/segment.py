"""Stillness segmentation: rests from windowed accel and gyro variance, turns between them.

A sample is still when the variance of both accel and gyro over a window
centred on it (by time, so irregular or bursty stamps are fine) stays below a
threshold factor times the noise variance. The noise variance is measured over
an initial rest when ``initial_rest_s`` > 0, else robustly as a low quantile of
the windowed variance over the whole session. Runs of still samples longer
than ``min_rest_s`` become rests; gaps longer than ``max_gap_s`` split them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import schemas
from ..components import BoundSolver, Params, Stage
from ..errors import SolverError
from ..observations import Rests
from ..rotations import hold_intervals, pad_turns, quat_to_rotvec, turn_quaternions


class SegmentParams(Params):
    """Units are in the names: ``window_s`` window of the variance test; ``min_rest_s``
    shortest rest kept; ``max_gap_s`` a stamp gap that splits a rest;
    ``accel_threshold``, ``gyro_threshold``: factors on the noise variance;
    ``initial_rest_s``: seconds at the start known to be still (0: robust estimate);
    ``noise_quantile``: the quantile of windowed variance taken as noise when robust;
    ``trim_s``: dropped from both ends of each rest."""

    window_s: float = Field(1.0, gt=0)
    min_rest_s: float = Field(2.0, ge=0)
    max_gap_s: float = Field(0.5, gt=0)
    accel_threshold: float = Field(4.0, gt=0)
    gyro_threshold: float = Field(4.0, gt=0)
    initial_rest_s: float = Field(0.0, ge=0)
    noise_quantile: float = Field(0.1, ge=0, le=1)
    trim_s: float = Field(0.0, ge=0)


def xyz(table: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (k,) int64, values (k, 3)) of a sample table."""
    return table.column("t_ns").to_numpy(), np.column_stack(
        [table.column(c).to_numpy() for c in ("x", "y", "z")])


def windowed_variance(t_s: np.ndarray, v: np.ndarray, window_s: float) -> np.ndarray:
    """(k,) trace of the covariance of ``v`` (k, 3) over [t - w/2, t + w/2] per sample."""
    v = v - np.median(v, axis=0)  # conditioning of the running sums
    c1 = np.vstack([np.zeros((1, 3)), np.cumsum(v, axis=0)])
    c2 = np.vstack([np.zeros((1, 3)), np.cumsum(v * v, axis=0)])
    lo = np.searchsorted(t_s, t_s - window_s / 2, "left")
    hi = np.searchsorted(t_s, t_s + window_s / 2, "right")
    n = (hi - lo).astype(float)
    s1, s2 = c1[hi] - c1[lo], c2[hi] - c2[lo]
    var = (s2 - s1 * s1 / n[:, None]) / np.maximum(n - 1, 1)[:, None]
    out = var.sum(axis=1)
    out[n < 3] = np.inf  # too few samples to call it still
    return out


def noise_level(t_s: np.ndarray, var: np.ndarray, p: SegmentParams, what: str,
                threshold: float = 4.0) -> float:
    """The noise variance: over the initial rest, checked to be still (below ``threshold``
    times the robust level of the whole session), else the robust level."""
    robust = float(np.quantile(var[np.isfinite(var)], p.noise_quantile)) if np.isfinite(var).any() \
        else float("nan")
    if p.initial_rest_s > 0:
        sel = t_s <= t_s[0] + p.initial_rest_s
        level = float(np.median(var[sel & np.isfinite(var)])) if (sel & np.isfinite(var)).any() \
            else float("nan")
        if np.isfinite(level) and robust > 0 and level > threshold * robust:
            raise SolverError(
                f"segmentation: the first {p.initial_rest_s:g} s (initial_rest_s) are not still: the "
                f"{what} variance there is {level / robust:.3g} times that of the quietest windows "
                f"(still is below {threshold:g}); the recording does not start with a rest: set "
                "initial_rest_s = 0 (noise from the quietest windows) or trim the recording")
    else:
        level = robust
    if not np.isfinite(level) or level <= 0:
        raise SolverError(f"segmentation: cannot estimate the {what} noise (constant or empty signal); "
                          "give initial_rest_s over a true rest")
    return level


def find_rests(t_ns: np.ndarray, still: np.ndarray, p: SegmentParams) -> list[tuple[int, int]]:
    """Index ranges [i0, i1] (inclusive) of still runs, split at gaps, trimmed, long enough."""
    t_s = (t_ns - t_ns[0]) * 1e-9
    breaks = np.flatnonzero(np.diff(t_s) > p.max_gap_s) + 1
    still = still.copy()
    still[breaks] = False  # a gap ends a run
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    out = []
    for i0, i1 in zip(starts, ends, strict=True):
        if p.trim_s:
            i0 = int(np.searchsorted(t_s, t_s[i0] + p.trim_s))
            i1 = int(np.searchsorted(t_s, t_s[i1] - p.trim_s, "right")) - 1
        if i1 > i0 and t_s[i1] - t_s[i0] >= p.min_rest_s:
            out.append((int(i0), int(i1)))
    return out


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
    t_g, w = xyz(inputs["gyro"])
    if len(t_a) < 10 or len(t_g) < 10:
        raise SolverError("segmentation: accel and gyro need at least 10 samples each")
    t0 = int(min(t_a[0], t_g[0]))
    ta_s, tg_s = (t_a - t0) * 1e-9, (t_g - t0) * 1e-9
    va = windowed_variance(ta_s, a, params.window_s)
    vg = windowed_variance(tg_s, w, params.window_s)
    na = noise_level(ta_s, va, params, "accelerometer", params.accel_threshold)
    ng = noise_level(tg_s, vg, params, "gyroscope", params.gyro_threshold)
    vg_at_a = np.interp(ta_s, tg_s, np.where(np.isfinite(vg), vg, 1e300))
    still = (va < params.accel_threshold * na) & (vg_at_a < params.gyro_threshold * ng)
    runs = find_rests(t_a, still, params)
    if not runs:
        raise SolverError("segmentation: no rest found; lower min_rest_s or raise the thresholds, "
                          "or check that the recording holds stationary intervals")
    bounds = np.array([[t_a[i0], t_a[i1]] for i0, i1 in runs], dtype=np.int64)
    mean, cov, counts = {}, {}, {}
    for s in ("accel", "gyro", "mag"):
        if s in inputs:
            mean[s], cov[s], counts[s] = rest_stats(inputs[s], bounds)
    if "temperature" in inputs:
        tt = inputs["temperature"].column("t_ns").to_numpy()
        TT = inputs["temperature"].column("temperature").to_numpy()
        temp = np.array([TT[(tt >= a0) & (tt <= b0)].mean() if np.any((tt >= a0) & (tt <= b0))
                         else np.interp(0.5 * (a0 + b0), tt, TT) for a0, b0 in bounds])
    else:
        temp = np.full(len(bounds), np.nan)
    rests = Rests((bounds[:, 0] - t0) * 1e-9, (bounds[:, 1] - t0) * 1e-9, counts["accel"], mean, cov,
                  temp, counts, t0)
    return {"rests": rests.to_table(), "turns": turns_table(rests, t_g, w, t0)}


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
    angles = np.degrees(np.linalg.norm(quat_to_rotvec(turn_quaternions(
        *pad_turns(ts, ws, hold_intervals))), axis=1)) if m > 0 else np.zeros(0)
    table = pa.table({
        "index": np.arange(m, dtype=np.int64), "rest_before": np.arange(m, dtype=np.int64),
        "rest_after": np.arange(1, m + 1, dtype=np.int64), "t_start_ns": starts, "t_end_ns": ends,
        "duration_s": (ends - starts) * 1e-9, "n_samples": np.array([len(t) for t in ts], np.int64),
        "angle_deg": angles,
    })
    return schemas.stamp(table, "turns", {"imupipe.t0_ns": str(t0)})


STAGE = Stage(
    name="segment_stillness", version="2", func=segment,
    inputs={"accel": "accel", "gyro": "gyro", "mag": "mag", "temperature": "temperature"},
    outputs={"rests": "rests", "turns": "turns"}, params=SegmentParams,
    optional_inputs=frozenset({"mag", "temperature"}),
    description="rests from accel and gyro variance; turns between consecutive rests",
)
COMPONENTS = [STAGE]

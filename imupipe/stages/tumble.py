"""Quasi-static windows of a free tumble, as ``rests``: for a recording with no rests at all.

A hand tumble never stops, but in its calmer moments the accelerometer reads
gravity to within the motion's small linear acceleration. The session is cut
into ``window_s`` windows on the accelerometer's clock; each stream's samples in
a window give its mean and one-sample covariance (the ``rests`` schema, so the
ordinary calibrate stages take them). The calmest ``keep_fraction`` of windows
by accelerometer variance are kept, in each of 26 direction bins (calm moments
cluster in a few orientations), and of those the ones whose ``|a|`` is within
``max_norm_dev`` of the median ``|a|`` (gravity, not a push). What motion remains
enters each window's covariance, so a moving window weighs less.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from ..components import BoundSolver, Params, Stage
from ..errors import SolverError
from ..observations import Rests
from .segment import xyz


class TumbleParams(Params):
    """``window_s``: window length; ``keep_fraction``: the calmest share of windows kept (by
    accelerometer variance); ``max_norm_dev``: relative |a| deviation from the median allowed."""

    window_s: float = Field(0.2, gt=0)
    keep_fraction: float = Field(0.5, gt=0, le=1)
    max_norm_dev: float = Field(0.05, gt=0)


def window_stats(t: np.ndarray, v: np.ndarray, edges: np.ndarray):
    """Mean (n, 3), one-sample covariance (n, 3, 3), count (n,) of ``v`` in [edges[i], edges[i+1])."""
    n = len(edges) - 1
    k = np.searchsorted(edges, t, "right") - 1
    ok = (k >= 0) & (k < n)
    k, v = k[ok], v[ok]
    count = np.bincount(k, minlength=n)
    s1 = np.stack([np.bincount(k, v[:, i], n) for i in range(3)], axis=1)
    s2 = np.stack([np.bincount(k, v[:, i] * v[:, j], n) for i in range(3) for j in range(3)],
                  axis=1).reshape(n, 3, 3)
    c = np.maximum(count, 1)[:, None]
    mean = s1 / c
    cov = (s2 - np.einsum("ni,nj->nij", s1, s1) / c[:, :, None]) / np.maximum(count - 1, 1)[:, None, None]
    return mean, cov, count


def tumble_windows(inputs: Mapping[str, pa.Table], params: TumbleParams, solver: BoundSolver | None):
    ta, a = xyz(inputs["accel"])
    t0 = int(ta[0])
    step = int(round(params.window_s * 1e9))
    edges = np.arange(t0, int(ta[-1]) + step, step, dtype=np.int64)
    if len(edges) < 14:
        raise SolverError(f"tumble_windows: the recording spans {(ta[-1] - t0) * 1e-9:.1f} s, "
                          f"under 13 windows of {params.window_s} s; tumble for a minute or more")
    stats = {s: window_stats(*xyz(inputs[s]), edges) for s in ("accel", "gyro", "mag") if s in inputs}
    enough = np.all([c >= 2 for _, _, c in stats.values()], axis=0)
    var = np.trace(stats["accel"][1], axis1=1, axis2=2)
    norm = np.linalg.norm(stats["accel"][0], axis=1)
    idx = np.flatnonzero(enough)
    if len(idx) == 0:
        raise SolverError("tumble_windows: no window holds two samples of every stream; "
                          "raise window_s")
    # the calmest share within each of 26 direction bins: calm moments cluster in a few
    # orientations, and the fits need them all
    u = stats["accel"][0][idx] / np.maximum(norm[idx], 1e-12)[:, None]
    dirs = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)], float) - 1
    bins = np.argmax(u @ (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).T, axis=1)
    calm = np.concatenate([
        sel[var[sel] <= np.quantile(var[sel], params.keep_fraction)]
        for b in np.unique(bins) for sel in [idx[bins == b]]])
    calm.sort()
    g = np.median(norm[calm])
    keep = calm[np.abs(norm[calm] / g - 1) <= params.max_norm_dev]
    if len(keep) < 12:
        raise SolverError(f"tumble_windows: only {len(keep)} calm windows of {len(idx)}; "
                          "tumble more slowly, or raise keep_fraction / max_norm_dev")
    mean = {s: v[0][keep] for s, v in stats.items()}
    cov = {s: v[1][keep] for s, v in stats.items()}
    counts = {s: v[2][keep].astype(np.int64) for s, v in stats.items()}
    if "temperature" in inputs:
        tt = inputs["temperature"].column("t_ns").to_numpy()
        TT = inputs["temperature"].column("temperature").to_numpy().astype(float)
        temp = np.interp(0.5 * (edges[keep] + edges[keep + 1]), tt, TT)
    else:
        temp = np.full(len(keep), np.nan)
    rests = Rests((edges[keep] - t0) * 1e-9, (edges[keep + 1] - 1 - t0) * 1e-9, counts["accel"],
                  mean, cov, temp, counts, t0)
    return {"rests": rests.to_table()}


STAGE = Stage(
    name="tumble_windows", version="1", func=tumble_windows,
    inputs={"accel": "accel", "gyro": "gyro", "mag": "mag", "temperature": "temperature"},
    outputs={"rests": "rests"}, params=TumbleParams,
    optional_inputs=frozenset({"mag", "temperature"}),
    description="the calmest short windows of a free tumble, as rests (no true rests needed)",
)
COMPONENTS = [STAGE]

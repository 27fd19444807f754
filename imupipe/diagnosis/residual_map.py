"""Where the model fails: chi2/dof of whitened residuals per cell, ranked, with FDR control.

The rows of the fitted per-sample model (``evaluate.Evaluation``: rest means,
turn rows -- the gyro's evidence in motion --, every accelerometer sample inside
the motions) are binned into cells: sensor x axis x regime (static / motion) x
one regime variable at a time (``|omega|``, ``|alpha|``, temperature, its rate,
time since power-on, which axis gravity is along, time in the session). A cell's
statistic is the sum of its squared whitened residuals against its effective
degrees of freedom (rows minus their leverage: what the fitted nuisances and
parameters absorb), so ``chi2/dof`` is 1 in expectation when the model and its
noise model hold. Within-rest scatter about each rest's mean (the noise model's
own check: vibrating or interfered rests) forms cells of its own.

Each cell's upper-tail p-value comes from the chi-square distribution; cells are
flagged by Benjamini-Hochberg across all cells at ``q``; flagged cells come first,
strongest evidence first. Change points of the rests' whitened residual series
(bias jumps; ``ruptures``' PELT with its least-squares cost, vectorised, and a penalty for
few false alarms) and isolated events join the map as events.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import tails
from ..columns import equals, vectors
from .evaluate import Evaluation
from .events import Event
from .forward import BLOCKS

Q_FDR = 0.05
MIN_DOF = 5.0
AXES = ("x", "y", "z")
BINS = {
    "|omega| rad/s": [0.0, 0.05, 0.2, 0.5, 1.0, 2.0, np.inf],
    "|alpha| rad/s^2": [0.0, 0.2, 1.0, 3.0, 10.0, np.inf],
    "time since power-on s": [0.0, 60.0, 300.0, 900.0, np.inf],
    "temperature rate degC/s": [-np.inf, -2e-3, 2e-3, np.inf],
}
GRAVITY_CELLS = ("+x up", "-x up", "+y up", "-y up", "+z up", "-z up")
TIME_WINDOWS = 10
BATCH_S = 5.0  # time batches whose spread measures the rows' correlation
MIN_BATCHES = 10
# A cell is tested against chi2/dof = 1.05, not 1: with 1e5 rows a 1 % mismatch of the noise
# model is "significant" but is no missing physics (the residual sd 0.5 % off).
EXCESS_MARGIN = 0.05
LONE_LEVEL = 0.001  # family-wise false-alarm rate of the lone-rest test over one rest series


@dataclass(frozen=True)
class Cell:
    sensor: str
    axes: tuple[str, ...]
    regime: str
    variable: str
    lo: float
    hi: float
    chi2: float
    dof: float
    windows: list[tuple[float, float]]
    batch_sd: float = 0.0  # sd of chi2/dof from the spread between time batches (0: too few)

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def p_value(self) -> float:
        """Excess over ``1 + EXCESS_MARGIN``: chi-square when the rows are independent; when the spread between
        ``BATCH_S`` batches shows them correlated (a slowly mis-modelled nuisance), the
        normal tail with that spread (an effective sample size), whichever is larger."""
        excess = 1 + EXCESS_MARGIN
        p = float(tails.chi2_sf(self.chi2 / excess, self.dof))
        if self.batch_sd > np.sqrt(2 / self.dof):
            p = max(p, float(tails.norm_sf((self.chi2_per_dof - excess) / self.batch_sd)))
        return p


@dataclass
class RowSet:
    """The rows a map is built from: whitened residual ``r`` (N,), degrees of freedom each
    contributes ``w`` (N,) (1 - leverage), and per row ``sensor``, ``axis`` (0-2, -1: all),
    ``regime`` (static | motion), ``t`` (s) and the regime variables ``var[name]`` (N,)."""

    r: np.ndarray
    w: np.ndarray
    sensor: np.ndarray
    axis: np.ndarray
    regime: np.ndarray
    t: np.ndarray
    var: dict[str, np.ndarray]
    family: str = "model"

    def take(self, sel: np.ndarray) -> RowSet:
        return RowSet(self.r[sel], self.w[sel], self.sensor[sel], self.axis[sel], self.regime[sel], self.t[sel],
                      {k: v[sel] for k, v in self.var.items()}, self.family)


def _gravity_cell(g: np.ndarray) -> np.ndarray:
    """Index into GRAVITY_CELLS of the axis most aligned with gravity (up), per row; -1 unknown."""
    ok = np.all(np.isfinite(g), axis=1)
    a = np.argmax(np.abs(np.where(ok[:, None], g, 0.0)), axis=1)
    sign = np.take_along_axis(g, a[:, None], 1)[:, 0] < 0
    return np.where(ok, 2 * a + sign, -1)


def model_rows(ev: Evaluation) -> RowSet:
    """The fitted model's data rows (rest means, turns, motion samples), with their regimes."""
    lin = ev.lin
    model = lin.model
    rows = lin.rows
    data = np.isin(rows.block, [BLOCKS.index(b) for b in ("accel_rest", "gyro_rest", "turn", "accel_motion")])
    idx = np.flatnonzero(data)
    block = rows.block[idx]
    name = np.array(BLOCKS)[block]
    sensor = np.where(np.isin(name, ["accel_rest", "accel_motion"]), "accel", "gyro")
    regime = np.where(np.isin(name, ["accel_rest", "gyro_rest"]), "static", "motion")
    t = rows.t[idx]
    samples = ev.samples
    st = samples.column("t_s").to_numpy()
    acc_rows = equals(samples, "sensor", "accel")
    s_t = st[acc_rows]
    order = np.argsort(s_t)

    def at(col: str, times: np.ndarray) -> np.ndarray:
        values = samples.column(col).to_numpy(zero_copy_only=False)[acc_rows][order]
        return np.interp(times, s_t[order], values)

    grav = vectors(samples, "gravity")[acc_rows][order]
    g_at = np.stack([np.interp(t, s_t[order], grav[:, k]) for k in range(3)], 1) if len(s_t) else np.zeros((len(t), 3))
    T = model.temperature_at(t)
    var = {
        "|omega| rad/s": np.where(regime == "motion", at("omega_norm", t), 0.0),
        "|alpha| rad/s^2": np.where(regime == "motion", at("alpha_norm", t), 0.0),
        "time since power-on s": at("t_on_s", t),
        "temperature degC": T,
        "temperature rate degC/s": at("temperature_rate", t),
        "gravity along": _gravity_cell(g_at).astype(float),
        "time s": t,
    }
    # a turn's rows: its mean |omega| over the motion, not the knot interval's instant
    return RowSet(lin.r[idx], 1.0 - lin.leverage[idx], sensor, rows.axis[idx], regime, t, var)


def rest_scatter_rows(ev: Evaluation) -> RowSet:
    """Within-rest scatter: each rest sample's whitened residual about its rest's mean (the
    mean is the model rows' business), ``(n_i - 1) / n_i`` degrees of freedom each."""
    s = ev.samples
    keep = equals(s, "kind", "rest")
    sensor = np.where(equals(s, "sensor", "gyro")[keep], "gyro", "accel")
    seg = s.column("segment").to_numpy()[keep]
    t = s.column("t_s").to_numpy()[keep]
    w = vectors(s, "whitened")[keep]
    key = 2 * seg + (sensor == "gyro")
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    means = np.zeros((len(counts), 3))
    np.add.at(means, inv, w)
    means /= counts[:, None]
    d = (w - means[inv]).ravel()
    n = np.repeat(counts[inv], 3)
    rows = len(d)
    T = np.repeat(s.column("temperature").to_numpy()[keep], 3)
    return RowSet(d, (n - 1) / n, np.repeat(sensor, 3), np.tile(np.arange(3), len(t)), np.full(rows, "static"),
                  np.repeat(t, 3), {"time s": np.repeat(t, 3), "temperature degC": T}, family="noise")


def windows(t: np.ndarray, contrib: np.ndarray, gap: float = 2.0, keep: int = 12) -> list[tuple[float, float]]:
    """Time windows (s) covered by rows at ``t``, joined across gaps < ``gap``; the ``keep``
    windows holding most of the chi2 excess, in time order."""
    if not len(t):
        return []
    if np.any(t[1:] < t[:-1]):  # a cell's rows mostly come in time order already
        o = np.argsort(t)
        t, contrib = t[o], contrib[o]
    starts = window_starts(t, gap)
    ends = np.r_[starts[1:], len(t)]
    return strongest(t[starts], t[ends - 1], np.add.reduceat(contrib, starts), keep)


def window_starts(t: np.ndarray, gap: float = 2.0) -> np.ndarray:
    """Where each window of sorted times ``t`` starts: they are joined across gaps < ``gap`` s."""
    return np.r_[0, np.flatnonzero(np.diff(t) > gap) + 1]


def strongest(first: np.ndarray, last: np.ndarray, excess: np.ndarray, keep: int = 12) -> list[tuple[float, float]]:
    """The ``keep`` windows (``first``, ``last`` s) of most ``excess``, in time order."""
    best = sorted(range(len(first)), key=lambda i: -excess[i])[:keep]
    return sorted((float(first[i]), float(last[i])) for i in best)


def _bins(name: str, x: np.ndarray) -> list[tuple[float, float]]:
    if name in BINS:
        e = BINS[name]
        return list(zip(e[:-1], e[1:], strict=True))
    if name == "gravity along":
        return [(float(i), float(i)) for i in range(6)]
    finite = x[np.isfinite(x)]
    if not len(finite) or np.ptp(finite) <= (1.0 if name.startswith("temperature") else 0.0):
        return []
    n = TIME_WINDOWS if name == "time s" else 4
    e = np.quantile(finite, np.linspace(0, 1, n + 1)) if name != "time s" else \
        np.linspace(finite.min(), finite.max(), n + 1)
    e[-1] = np.nextafter(e[-1], np.inf)
    return [(float(a), float(b)) for a, b in zip(e[:-1], e[1:], strict=True) if b > a]


def levels(a: np.ndarray) -> list:
    """The distinct values of ``a`` (labels: no NaN), sorted: one pass per value (a few), where
    ``np.unique`` hashes or sorts every row."""
    out = []
    while len(a):
        out.append(a[0])
        a = a[1:][a[1:] != a[0]]  # shrinks at every pass
    return sorted(out)


def pairs(sensor: np.ndarray, regime: np.ndarray) -> list[tuple[tuple[str, str], np.ndarray]]:
    """The (sensor, regime) pairs of rows, sorted, each with its rows' indices."""
    out = []
    for s in levels(sensor):
        of_sensor = sensor == s
        for g in levels(regime[of_sensor]):
            out.append(((s, g), np.flatnonzero(of_sensor & (regime == g))))
    return out


def cells(rs: RowSet, groups: list | None = None) -> list[Cell]:
    """Every cell of ``rs`` with at least ``MIN_DOF`` degrees of freedom (``groups``: its
    ``pairs``, when already found)."""
    out = []
    for (sensor, regime), idx in pairs(rs.sensor, rs.regime) if groups is None else groups:
        axis = rs.axis[idx]
        by_axes = [((AXES[a],), idx[axis == a]) for a in levels(axis) if a >= 0]
        by_axes.append((tuple(AXES), idx))
        for axes, rows in by_axes:
            out += _cells_of(rs, rows, sensor, axes, regime)
    return out


def _cells_of(rs: RowSet, rows: np.ndarray, sensor: str, axes: tuple[str, ...], regime: str) -> list[Cell]:
    """The cells of ``rows`` (sorted indices into ``rs``): all of them, then each bin of each
    regime variable (taken one at a time: a long recording's rows are not copied whole)."""
    r, w, t = rs.r[rows], rs.w[rows], rs.t[rows]

    def make(variable: str, lo: float, hi: float, m: np.ndarray | None = None) -> Cell | None:
        r_m, w_m, t_m = (r, w, t) if m is None else (r[m], w[m], t[m])
        dof = float(w_m.sum())
        if dof < MIN_DOF:
            return None
        r2 = r_m ** 2
        return Cell(sensor, axes, regime, variable, lo, hi, float(r2.sum()), dof,
                    windows(t_m, r2 - w_m), _batch_sd(t_m, r2, w_m))

    label = "all" if rs.family == "model" else "within-rest scatter"
    out = [make(label, -np.inf, np.inf)]
    for name, x in rs.var.items():
        if regime == "static" and name in ("|omega| rad/s", "|alpha| rad/s^2"):
            continue
        x = x[rows]
        for lo, hi in _bins(name, x):
            m = (x == lo) if name == "gravity along" else (x >= lo) & (x < hi)
            if np.count_nonzero(m) == len(rows):
                continue  # the bin is the whole set: the "all" cell says it
            v = name if rs.family == "model" else f"{name} (within-rest scatter)"
            out.append(make(v, lo, hi, m))
    return [c for c in out if c is not None]


def _batch_sd(t: np.ndarray, r2: np.ndarray, w: np.ndarray) -> float:
    """Standard error of sum(r2) / sum(w) from the spread of its ``BATCH_S`` time batches
    (ratio estimator; 0 with fewer than ``MIN_BATCHES``)."""
    if not len(t):
        return 0.0
    b = np.floor((t - t.min()) / BATCH_S).astype(np.int64)
    S, W, n = np.bincount(b, r2), np.bincount(b, w), np.bincount(b)
    S, W = S[n > 0], W[n > 0]  # the batches that hold rows
    B = len(S)
    if B < MIN_BATCHES:
        return 0.0
    R = S.sum() / W.sum()
    return float(np.sqrt(B / (B - 1) * np.sum((S - R * W) ** 2)) / W.sum())


def benjamini_hochberg(p: np.ndarray, q: float = Q_FDR) -> np.ndarray:
    """(n,) bool: discoveries of the Benjamini-Hochberg step-up procedure at level ``q``."""
    p = np.asarray(p, float)
    n = len(p)
    if not n:
        return np.zeros(0, bool)
    order = np.argsort(p)
    below = p[order] <= q * np.arange(1, n + 1) / n
    k = np.flatnonzero(below).max() + 1 if below.any() else 0
    out = np.zeros(n, bool)
    out[order[:k]] = True
    return out


def pelt_l2(z: np.ndarray, pen: float, min_size: int = 3) -> list[int]:
    """The break points (segment ends before the last) of ``ruptures.Pelt(model="l2",
    min_size=min_size, jump=1).fit(z).predict(pen)``: the partition of ``z`` (n, d) into
    segments of at least ``min_size`` minimising their squared deviations from their means plus
    ``pen`` each. ruptures' recursion and pruning, each step vectorised over the candidate
    starts with cumulative sums: its Python loop runs candidates x time, and on a series without
    a change PELT prunes none (10 s of a 4 h session's map; ``bench/change_points.py``)."""
    z = z.reshape(len(z), -1)
    n = len(z)
    S = np.vstack([np.zeros(z.shape[1]), np.cumsum(z, axis=0)])
    Q = np.r_[0.0, np.cumsum((z**2).sum(axis=1))]
    F = np.full(n + 1, np.inf)  # the best total up to each end (inf: no partition ends there)
    F[0] = 0.0
    start = np.zeros(n + 1, int)
    admissible = np.zeros(1, int)
    for t in [*range(min_size, n), n]:
        c = np.r_[admissible, t - min_size]
        c = c[np.isfinite(F[c])]
        d = S[t] - S[c]
        total = F[c] + (Q[t] - Q[c] - np.einsum("ij,ij->i", d, d) / (t - c)) + pen
        best = int(np.argmin(total))
        F[t], start[t] = total[best], c[best]
        admissible = c[total <= F[t] + pen]
    bkps, t = [], n
    while t > 0:
        t = int(start[t])
        bkps.append(t)
    return sorted(bkps[:-1])


def lone_rests(z: np.ndarray, level: float = LONE_LEVEL) -> tuple[np.ndarray, np.ndarray]:
    """Indices (k,) of the rests of a whitened rest-mean residual series ``z`` (n, 3) that stand
    off from both neighbours while the neighbours agree (chi-square tests, Bonferroni over the
    series at ``level``), and their offsets (k, 3) from the neighbours' mean in standard errors:
    a rest that was not still, or a momentary bias jump. A step between rests never qualifies:
    its neighbours' difference is three times the rest's own statistic.
    Where the whole series scatters more than the model says (its median neighbour difference
    beyond chi-square's), the tests take that scatter as their unit: a lone rest stands out
    from the series, not only from the noise model."""
    if len(z) < 3:
        return np.zeros(0, int), np.zeros((0, 3))
    off = (z[1:-1] - 0.5 * (z[:-2] + z[2:])) / np.sqrt(1.5)  # unit variance per axis under the model
    apart = ((z[:-2] - z[2:]) ** 2).sum(axis=1) / 2  # chi-square 3, as (off**2).sum(axis=1)
    crit = tails.chi2_isf(level / len(z), 3) * max(1.0, float(np.median(apart)) / tails.chi2_ppf(0.5, 3))
    lone = np.flatnonzero(((off**2).sum(axis=1) > crit) & (apart <= crit))
    return lone + 1, off[lone]


def change_points(ev: Evaluation, penalty_sd: float = 4.0) -> list[Event]:
    """Mean shifts in each sensor's rest-mean whitened residual series (bias jumps between
    rests): PELT (``pelt_l2``) on the series, the penalty set so that a pure white series
    yields a change point rarely; each kept when its step exceeds ``penalty_sd`` standard errors.
    A lone rest (``lone_rests``) is an event of its own and left out of the search (PELT would
    place a step on each side of it)."""
    lin = ev.lin
    out = []
    for block, sensor in (("gyro_rest", "gyro"), ("accel_rest", "accel")):
        sel = lin.rows.of(block)
        z = lin.r[sel].reshape(-1, 3)
        t = lin.rows.t[sel].reshape(-1, 3)[:, 0]
        lone, offsets = lone_rests(z)
        for i, off in zip(lone, offsets, strict=True):
            ax = int(np.argmax(np.abs(off)))
            out.append(Event("lone_rest", sensor, (float(t[i]), float(t[i])),
                             f"the {sensor} rest at {t[i]:.1f} s stands {abs(off[ax]):.1f} standard errors off "
                             f"(on {AXES[ax]}) from the rests either side, which agree: it was not still (a slow "
                             "turn or a knock inside it) or the bias jumped for it alone"))
        z, t = np.delete(z, lone, axis=0), np.delete(t, lone)
        n = len(z)
        if n < 12:
            continue
        pen = 3 * 2 * np.log(n)  # 3-dimensional mean shift: a conservative BIC
        bkps = pelt_l2(z, pen)
        edges = [0, *bkps, n]
        for k, b in enumerate(bkps):
            left, right = z[edges[k]:b], z[b:edges[k + 2]]
            step = left.mean(0) - right.mean(0)
            se = np.sqrt(1 / len(left) + 1 / len(right))
            if np.abs(step).max() / se < penalty_sd:
                continue
            ax = AXES[int(np.argmax(np.abs(step)))]
            out.append(Event("change_point", sensor, (float(t[b - 1]), float(t[b])),
                             f"the {sensor} rest residuals step by {np.abs(step).max() / se:.1f} standard "
                             f"errors (largest on {ax}) between the rests at {t[b - 1]:.1f} s and {t[b]:.1f} s"))
    return out


def residual_map(ev: Evaluation, session: str = "", q: float = Q_FDR,
                 extra: Callable[[], tuple[RowSet, ...]] = tuple, keep_jacobians: bool = True) -> dict:
    """The ``residual_map.json`` document of ``spec/contracts.md`` for an evaluation; ``extra()``:
    rows of triads outside the per-sample model (the magnetometer's, ``magnetic``);
    ``keep_jacobians=False``: the fit's Jacobians are dropped once the structure cells are
    scored (nothing after them needs them; a diagnosis does)."""
    from .library import structure_cells  # it builds on select, which builds on this module

    structure = structure_cells(ev.lin)  # first: its working memory is free again for the rows' cells
    if not keep_jacobians:
        ev.lin.forget_jacobians()
    # each family of rows is let go once its cells and blocks are found: one held at a time
    model_cells = cells(model_rows(ev))
    noise_cells, row_blocks = _cells_and_blocks(rest_scatter_rows(ev))
    extra_cells = []
    for rs in extra():  # after the structure cells, whose working memory is then free
        c, b = _cells_and_blocks(rs)
        extra_cells += c
        row_blocks += b
    all_cells = model_cells + noise_cells + structure + extra_cells
    p = np.array([c.p_value for c in all_cells])
    flagged = benjamini_hochberg(p, q)
    # flagged first, by the misfit they carry (chi2 - dof: a log-likelihood excess; p-values
    # underflow to 0 for every strong cell), then the rest by p-value
    order = sorted(range(len(all_cells)),
                   key=lambda i: (not flagged[i], -(all_cells[i].chi2 - all_cells[i].dof) if flagged[i] else p[i]))
    blocks = []
    for name, b in ev.lin.blocks().items():
        sensor = {"walk_gyro": "gyro", "walk_accel": "accel", "k_prior": "prior"}.get(name, name.split("_")[0])
        if name == "turn":
            sensor = "gyro"
        kind = {"accel_rest": "rest", "gyro_rest": "rest", "turn": "motion", "accel_motion": "motion"}.get(name, "prior")
        blocks.append({"block": name, "sensor": sensor, "kind": kind, "chi2": b["chi2"], "dof": b["dof"],
                       "chi2_per_dof": b["chi2_per_dof"], "rows": b["rows"]})
        if name in ev.white_chi2 and b["dof"] > 0:  # before the recording's own (coloured) noise model
            blocks[-1]["chi2_per_dof_white"] = ev.white_chi2[name] / b["dof"]
    blocks += row_blocks
    cell_docs = []
    for rank, i in enumerate(order):
        c = all_cells[i]
        cell_docs.append({
            "sensor": c.sensor, "axes": list(c.axes), "regime": c.regime, "variable": c.variable,
            "range": [_json_edge(c.lo), _json_edge(c.hi)] if c.variable != "gravity along"
            else [GRAVITY_CELLS[int(c.lo)]] * 2,
            "windows": [list(w) for w in c.windows], "chi2": c.chi2,
            "chi2_per_dof": c.chi2_per_dof, "dof": c.dof, "p_value": float(p[i]), "flagged": bool(flagged[i]),
            "rank": rank,
        })
        if c.variable == "structure":
            cell_docs[-1]["terms"] = c.terms
    events = list(ev.events) + change_points(ev)
    return {"session": session, "blocks": blocks, "cells": cell_docs,
            "events": [e.to_dict() for e in sorted(events, key=lambda e: e.window[0])],
            "noise_model": noise_summary(ev), "fdr_q": q}


def _cells_and_blocks(rs: RowSet) -> tuple[list[Cell], list[dict]]:
    """The cells of rows outside the fitted model (within-rest scatter, the magnetometer's) and
    their blocks: chi2 and dof per (sensor, regime)."""
    groups = pairs(rs.sensor, rs.regime)
    out = []
    for (sensor, regime), m in groups:
        c2, dof = float((rs.r[m] ** 2).sum()), float(rs.w[m].sum())
        kind = "rest" if regime == "static" else "motion"
        name = f"{sensor}_rest_samples" if rs.family == "noise" else f"{sensor}_{kind}"
        out.append({"block": name, "sensor": str(sensor), "kind": kind,
                    "chi2": c2, "dof": dof, "chi2_per_dof": c2 / dof if dof else None, "rows": len(m)})
    return cells(rs, groups), out


def _json_edge(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def noise_summary(ev: Evaluation) -> dict:
    """The noise model the map whitened with: one sample's sigma per axis and the walks."""
    n = ev.lin.model.noise
    return {"accel_sample_sigma": np.sqrt(np.diag(n.accel_sample)).tolist(),
            "gyro_sample_sigma": np.sqrt(np.diag(n.gyro_sample)).tolist(),
            "accel_bias_walk_sigma": np.sqrt(n.q_accel).tolist(), "gyro_bias_walk_sigma": np.sqrt(n.q_gyro).tolist(),
            "units": "accel m/s^2 (per sqrt(s) for walks), gyro rad/s; raw axes"}

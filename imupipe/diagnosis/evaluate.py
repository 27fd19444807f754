"""Predict every sample of a recording under a calibration, and whiten what is left.

``evaluate`` takes a session's raw streams, its segmentation and a calibration
(any method's), builds the forward model in per-sample mode
(``forward.JointModel``: rests, turns and every accelerometer sample inside the
motions), profiles its nuisances (gravity directions, bias walks, the attitude
path of every motion) with the calibration held fixed, and returns the fitted
linearisation plus a table with one row per raw sample of every triad:
time, time since power-on, segment id and kind, temperature and its rate,
``|omega|``, ``|alpha|``, the gravity direction in body axes, the predicted raw
reading, the residual and the whitened residual.

Motions that cannot be predicted sample by sample are not integrated across
silently: a motion that holds a gap, a shock or a splice (``events``) is left
out whole, and one whose accelerometer shows the unit being carried (the
residual, turned to the motion's start frame and integrated twice, moves it by
more than ``TRANSLATION_M``: a lever arm moves it by at most twice its length)
keeps only its end-points. Each becomes an event of the residual map.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import pyarrow as pa

from .. import schemas, tails
from ..allan import batch_variance_ratio
from ..models import T_REF_C, TriadCalibration
from ..observations import Rests, Turns
from ..solvers.joint_ml import lower_gauge
from .attitude import Attitude, by_motion
from .events import Event
from .forward import JointModel, MotionAccel, Noise, Start, rest_temperature
from .linearised import Linearised, fit

TRANSLATION_M = 0.15  # a motion that moves the unit further than this is a carry, not a rotation
POWER_GAP_S = 1.0  # a gap in the samples longer than this is a power cycle (new turn-on bias)
EXCLUDING = ("gap", "shock", "splice", "saturation")  # events that forbid integrating across
THERMAL_SPAN_C = 1.0  # rests spanning less cannot tell k from the bias
ESS_BATCHES = 8  # batch means per rest that measure its samples' correlation
OUTLIER_SD = 4.0  # a rest whose noise level is further from the pool's is not white noise
SCREEN_ITER = 2  # iterations of the first fit, before the carries are found
FIT_TOL = 1e-7  # relative cost decrease that ends the fit (a final Gauss-Newton step polishes it)


@dataclass
class Evaluation:
    """``lin`` the fitted per-sample model (lower-triangular gauge), ``frame`` Q (gauge -> the
    calibration's frame), ``table`` the per-sample residual table or what forms it (``samples``
    forms it on first use: the map's structure cells, before, have the memory without it),
    ``events``, ``turn_index`` (m',) which of the session's turns the model kept."""

    lin: Linearised
    frame: np.ndarray
    table: pa.Table | Callable[[], pa.Table] | None
    events: list[Event] = field(default_factory=list)
    turn_index: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    white_chi2: dict[str, float] = field(default_factory=dict)  # rest blocks under white noise

    @property
    def samples(self) -> pa.Table | None:
        if callable(self.table):
            self.table = self.table()
        return self.table


def effective_counts(rests: Rests, streams: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> Rests:
    """The rests with each triad's sample count cut to its effective size where the samples
    inside the rests are correlated (a hand-held or vibrating support, a slow sway).

    The variance of each rest's mean is measured by ``ESS_BATCHES`` batch means and compared
    with the white-noise one: the median ratio over rests (per triad, at least 1) applies to
    every rest, and a rest whose own ratio exceeds the 99 % point of the white ratio
    (chi-square with ``ESS_BATCHES - 1`` dof) keeps its own."""
    crit = tails.chi2_ppf(0.99, ESS_BATCHES - 1) / (ESS_BATCHES - 1)
    counts = {}
    for sensor in ("accel", "gyro", "mag"):
        if not rests.has(sensor) or sensor not in streams:
            continue
        t, y = streams[sensor]
        n = np.maximum(rests.counts.get(sensor, rests.count), 1).astype(float)
        ratio = np.ones(len(rests))
        i0 = np.searchsorted(t, rests.t_start_s)
        i1 = np.searchsorted(t, rests.t_end_s, "right")
        for i in range(len(rests)):
            r = batch_variance_ratio(y[i0[i]:i1[i]], ESS_BATCHES)
            if r is not None and np.isfinite(r).any():
                ratio[i] = float(np.median(r[np.isfinite(r)]))
        factor = np.where(ratio > crit, ratio, max(1.0, float(np.median(ratio))))
        counts[sensor] = n / np.maximum(factor, 1.0)
    return Rests(rests.t_start_s, rests.t_end_s, rests.count, rests.mean, rests.cov, rests.temperature,
                 {**rests.counts, **counts}, rests.t0_ns)


def white_noise(rests: Rests, streams: Mapping[str, tuple[np.ndarray, np.ndarray]], sensor: str) -> np.ndarray:
    """(3, 3) one raw sample's white-noise covariance: the rests' successive differences pooled
    (a bias walk, a thermal drift or a rest's offset do not enter them; quantisation does, as
    it does the motions' samples), over the rests whose own level (trace) is within ``OUTLIER_SD``
    standard errors of the pool's, starting from the rests' median (a rest on a vibrating
    support is left out)."""
    t, y = streams[sensor]
    i0 = np.searchsorted(t, rests.t_start_s)
    i1 = np.searchsorted(t, rests.t_end_s, "right")
    n = np.maximum(i1 - i0 - 1, 0)
    D = np.zeros((len(n), 3, 3))  # each rest's sum of d d' / 2 over its successive differences d
    for i, (a, b) in enumerate(zip(i0, i1, strict=True)):
        d = np.diff(y[a:b], axis=0)
        D[i] = d.T @ d / 2
    level = np.einsum("kii->k", D) / np.maximum(n, 1)
    centre = np.median(level[n > 0])  # the start: a bad rest cannot drag it
    for _ in range(3):
        use = (n > 0) & (np.abs(level / centre - 1) <= OUTLIER_SD / np.sqrt(np.maximum(n, 1)))
        pooled = D[use].sum(axis=0) / n[use].sum()
        centre = np.trace(pooled)
    return pooled


def power_on_rests(rests: Rests, t: np.ndarray) -> np.ndarray:
    """(n,) bool: rest i follows a gap in the samples longer than ``POWER_GAP_S`` (a power cycle)."""
    if len(t) < 2:
        return np.zeros(len(rests), bool)
    gaps = np.flatnonzero(np.diff(t) > POWER_GAP_S)
    ends = t[gaps]
    out = np.zeros(len(rests), bool)
    for e in ends:
        after = np.flatnonzero(rests.t_start_s > e)
        if len(after):
            out[after[0]] = True
    out[0] = False
    return out


def _overlaps(a0: np.ndarray, a1: np.ndarray, windows: list[tuple[float, float]]) -> np.ndarray:
    hit = np.zeros(len(a0), bool)
    for w0, w1 in windows:
        hit |= (a0 <= w1) & (a1 >= w0)
    return hit


def displacement(model: JointModel, lin: Linearised) -> np.ndarray:
    """(m,) m: how far each motion's unexplained acceleration carries the unit (start frame,
    integrated twice from rest), from the per-sample residuals of the fit ``lin`` (a first one:
    the attitude the gyro integrates from the rest before, good for seconds)."""
    acc = model.accel
    out = np.zeros(model.m)
    if not len(acc.t):
        return out
    x_l = lin.x_l
    P = model.unpack(lin.x_g)
    r = lin.r[model.rows.of("accel_motion")].reshape(-1, 3)
    e = np.linalg.solve(model.W_sample, r.T).T  # raw residual
    a_body = e @ np.linalg.inv(P["S_a"]).T  # m/s^2, instrument axes
    omega, _ = model._rates(P, x_l, derivatives=False)
    R = Attitude.integrate(model.quad, omega).rotation_at(model.accel_points)
    a_start = np.einsum("kij,kj->ki", R, a_body)
    for j, sel in enumerate(by_motion(acc.motion, model.m)):
        t = acc.t[sel]
        if len(t) < 3:
            continue
        dt = np.diff(t, prepend=t[0])
        v = np.cumsum(a_start[sel] * dt[:, None], axis=0)
        x = np.cumsum(v * dt[:, None], axis=0)
        out[j] = float(np.linalg.norm(x, axis=1).max())
    return out


def evaluate(streams: Mapping[str, tuple[np.ndarray, np.ndarray]], rests: Rests, turns: Turns,
             accel: TriadCalibration, gyro: TriadCalibration, gravity: float,
             q_accel: np.ndarray | None = None, q_gyro: np.ndarray | None = None,
             temperature: tuple[np.ndarray, np.ndarray] | None = None,
             events: list[Event] = (), knot_s: float = 0.25, max_iter: int = 10,
             refit: bool = True) -> Evaluation:
    """The per-sample model of a session under ``accel``/``gyro`` (held fixed).

    ``streams``: ``{"accel": (t (k,) s, y (k, 3)), "gyro": ...}`` raw, seconds from the
    session's first sample (the rests' clock); ``turns``: the motions between consecutive rests;
    ``q_*``: the bias random walks' intensities (per axis; the null model's,
    ``stages.residuals.null_walks``); ``temperature``: (t, T degC) for the samples inside motions;
    ``events``: those of the recording (motions overlapping a gap, shock, splice or saturation
    are left out); ``refit``: the calibration is refitted to every sample with the nuisances
    (the map then judges the model, not the estimation error of a calibration fitted to rest
    means and turn end-points only, which the samples of long turns resolve better); else it
    is held fixed.
    """
    events = list(events)
    t_a, y_a = streams["accel"]
    m = len(turns)
    t0 = np.array([t[0] if len(t) else np.nan for t in turns.t])
    t1 = np.array([t[-1] if len(t) else np.nan for t in turns.t])
    bad = _overlaps(np.nan_to_num(t0), np.nan_to_num(t1),
                    [e.window for e in events if e.kind in EXCLUDING]) if m else np.zeros(0, bool)
    keep = np.flatnonzero(~bad & np.array([len(t) > 1 for t in turns.t], bool)) if m else np.zeros(0, int)
    kept = turns.subset(keep)
    S0, Q = lower_gauge(accel.S)
    start = Start(S0, accel.b0, Q @ gyro.M, gyro.b0, accel.k, gyro.k)
    noise = replace(Noise.from_rests(rests, q_accel, q_gyro), accel_sample=white_noise(rests, streams, "accel"),
                    gyro_sample=white_noise(rests, streams, "gyro"))
    white_rests, rests = rests, effective_counts(rests, streams)
    power = power_on_rests(rests, t_a)
    # the temperature coefficients count among the calibration's parameters (leverage, and what a
    # candidate term is projected off) where the rests span enough temperature to determine them
    # (the stream's, as the model reads it: a pipeline's segmentation may not have been given it)
    T = rest_temperature(rests, temperature)
    thermal = bool(np.all(np.isfinite(T)) and len(T) and np.ptp(T) >= THERMAL_SPAN_C)

    def build(sampled_turns: np.ndarray, like: JointModel | None = None) -> JointModel:
        acc = MotionAccel.select(t_a, y_a, rests, kept)
        acc_keep = np.isin(acc.motion, sampled_turns)
        acc = MotionAccel(acc.t[acc_keep], acc.y[acc_keep], acc.motion[acc_keep])
        return JointModel(rests, kept, gravity, start, noise, fit_k=thermal, accel=acc, knot_s=knot_s,
                          power_on=power, temperature=temperature, like=like)

    sampled = np.arange(len(keep))
    model = build(sampled)
    # a first, short fit of the nuisances puts the attitude right (the gyro's calibration error,
    # integrated over a 20 s turntable turn, would pass for metres of travel), then the carries
    # are found and the final fit starts from it
    first = fit(model, max_iter=SCREEN_ITER, fixed_globals=True, tol=FIT_TOL, leverage=False)
    moved = displacement(model, first)
    carried = moved > TRANSLATION_M
    for j in np.flatnonzero(carried):
        events.append(Event("translation", "accel", (float(t0[keep[j]]), float(t1[keep[j]])),
                            f"the unit moved about {moved[j]:.2f} m during this motion (not a rotation "
                            "about a fixed point): its samples are left out, its end-points kept"))
    x_l = first.x_l
    del first  # its Jacobian: the final fit starts from its solution alone
    if carried.any():
        new = build(sampled[~carried], like=model)
        x_l = _remap(model.stages, new.stages, x_l)
        model = new
    lin = fit(model, max_iter=max_iter, x_l=x_l, fixed_globals=not refit, tol=FIT_TOL)
    model.forget_jacobian_places()  # the model's last Jacobian: the map reads lin's
    for j in np.flatnonzero(bad):
        what = [e.kind for e in events if e.kind in EXCLUDING and e.window[0] <= t1[j] and e.window[1] >= t0[j]]
        events.append(Event("excluded_motion", "gyro", (float(t0[j]), float(t1[j])),
                            f"motion {j} holds a {', '.join(sorted(set(what)))}: left out of the model"))
    excluded = [e.window for e in events if e.kind in ("translation", "excluded_motion")]
    samples = partial(sample_table, model, lin, streams, rests, Q, excluded)
    return Evaluation(lin, Q, samples, events, keep, _white_rest_chi2(model, lin, white_rests))


def _remap(old, new, x_l: np.ndarray) -> np.ndarray:
    """Locals of one layout as the start of another that differs only in how many knots some
    motions have (knots are last in each stage's block: keep the common prefix)."""
    out = np.zeros(new.size)
    for i in range(len(new.offsets) - 1):
        k = min(new.offsets[i + 1] - new.offsets[i], old.offsets[i + 1] - old.offsets[i])
        out[new.offsets[i]:new.offsets[i] + k] = x_l[old.offsets[i]:old.offsets[i] + k]
    return out


def _white_rest_chi2(model: JointModel, lin: Linearised, white: Rests) -> dict[str, float]:
    """chi2 of the rest blocks at the same fit, whitened as if the rests' samples were white."""
    out = {}
    for block, sensor, W in (("accel_rest", "accel", model.W_a), ("gyro_rest", "gyro", model.W_g)):
        e = np.linalg.solve(W, lin.r[lin.rows.of(block)].reshape(-1, 3, 1))[:, :, 0]  # raw residual
        L = np.linalg.cholesky(model.rest_cov(white, sensor))
        z = np.linalg.solve(L, e[:, :, None])[:, :, 0]
        out[block] = float((z ** 2).sum())
    return out


# --------------------------------------------------------------------------- per-sample table


KINDS = ("rest", "motion", "excluded")  # a sample's kind in the table, by its code


def _segments(rests: Rests, t: np.ndarray, power_times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per sample time: segment id (2 i for rest i, 2 i + 1 for the motion after it) and kind
    (its code in ``KINDS``)."""
    i = np.searchsorted(rests.t_start_s, t, "right") - 1
    in_rest = (i >= 0) & (t <= rests.t_end_s[np.maximum(i, 0)])
    seg = np.where(in_rest, 2 * i, 2 * i + 1)
    return seg, np.where(in_rest, 0, 1).astype(np.int8)


def _motion_rates(model: JointModel, omega: np.ndarray, Q: np.ndarray, t: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """|omega| and |alpha| (k,) at times ``t``: the calibrated rate of the motions (instrument
    frame) and its derivative, interpolated; zero outside the motions."""
    ms = model.motions
    w_norm, a_norm = np.zeros(len(t)), np.zeros(len(t))
    for sel in by_motion(ms.motion, ms.count):
        tj = ms.t[sel]
        if len(tj) < 2:
            continue
        wj = omega[sel] @ Q
        aj = np.gradient(wj, tj, axis=0)
        inside = slice(np.searchsorted(t, tj[0], "left"), np.searchsorted(t, tj[-1], "right"))  # t sorted
        w_norm[inside] = np.interp(t[inside], tj, np.linalg.norm(wj, axis=1))
        a_norm[inside] = np.interp(t[inside], tj, np.linalg.norm(aj, axis=1))
    return w_norm, a_norm


def sample_table(model: JointModel, lin: Linearised, streams, rests: Rests, Q: np.ndarray,
                 excluded: list[tuple[float, float]] = ()) -> pa.Table:
    """One row per raw accelerometer and gyro sample (see the module docstring), the accelerometer's
    first; each column one array (the stored table's digest then reads it in place, where a
    table of two chunks is copied whole to be digested)."""
    P = model.unpack(lin.x_g)
    sensors = ("accel", "gyro")
    sizes = [len(streams[s][0]) for s in sensors]
    n_all = sum(sizes)
    col = {name: np.empty(n_all) for name in ("t_s", "t_on_s", "temperature", "temperature_rate",
                                             "omega_norm", "alpha_norm")}
    vec = {name: np.full((n_all, 3), np.nan) for name in ("gravity", "predicted", "residual", "whitened")}
    segment, kinds = np.empty(n_all, np.int64), np.empty(n_all, np.int8)
    t_all = np.sort(np.concatenate([streams[s][0] for s in sensors]))
    power_times = t_all[np.flatnonzero(np.diff(t_all) > POWER_GAP_S) + 1] if len(t_all) > 1 else np.zeros(0)
    u_rest = model.gravity(lin.x_l)[0]
    waa, wab = model.walk_states(lin.x_l, "wa")
    wga, wgb = model.walk_states(lin.x_l, "wg")
    L = {"accel": np.linalg.cholesky(model.noise.accel_sample),
         "gyro": np.linalg.cholesky(model.noise.gyro_sample)}
    omega_all, _ = model._rates(P, lin.x_l, derivatives=False)
    u_motion = lin.gravity()[1]
    start = 0
    for sensor, n in zip(sensors, sizes, strict=True):
        t, y = streams[sensor]
        rows = slice(start, start + n)
        start += n
        seg, kind = _segments(rests, t, power_times)
        for w0, w1 in excluded:
            kind[(t >= w0) & (t <= w1) & (kind == 1)] = 2
        T = model.temperature_at(t)
        pred, whit, grav = vec["predicted"][rows], vec["whitened"][rows], vec["gravity"][rows]  # NaN: no model
        rest = kind == 0
        if rest.any():  # the rest's direction, the bias walk interpolated across the rest
            r = seg[rest] // 2
            frac = np.clip((t[rest] - rests.t_start_s[r]) / np.maximum(model.length[r], 1e-12), 0, 1)[:, None]
            grav[rest] = u_rest[r] @ Q
            if sensor == "accel":
                pred[rest] = model.accel_prediction(P, model.g * u_rest[r], t[rest],
                                                    (1 - frac) * waa[r] + frac * wab[r])
            else:
                pred[rest] = P["b_g"] + np.outer(T[rest] - T_REF_C, P["k_g"]) + (1 - frac) * wga[r] + frac * wgb[r]
            whit[rest] = np.linalg.solve(L[sensor], (y[rest] - pred[rest]).T).T
        if sensor == "accel" and len(model.accel.t):
            idx = np.searchsorted(t, model.accel.t)
            r_m = lin.r[lin.rows.of("accel_motion")].reshape(-1, 3)
            pred[idx] = model.accel.y - np.linalg.solve(model.W_sample, r_m.T).T
            whit[idx] = r_m
            grav[idx] = u_motion @ Q
        vec["residual"][rows] = y - pred
        col["omega_norm"][rows], col["alpha_norm"][rows] = _motion_rates(model, omega_all, Q, t)
        col["t_s"][rows], col["t_on_s"][rows] = t, t - _last_power_on(t, power_times, t_all)
        col["temperature"][rows] = T
        col["temperature_rate"][rows] = np.gradient(T, t) if n > 1 else 0.0
        segment[rows], kinds[rows] = seg, kind
    which = np.repeat(np.arange(len(sensors), dtype=np.int8), sizes)
    table = pa.table({
        "sensor": pa.DictionaryArray.from_arrays(which, sensors).cast(pa.string()),
        "t_s": col["t_s"], "t_on_s": col["t_on_s"], "segment": segment,
        "kind": pa.DictionaryArray.from_arrays(kinds, KINDS).cast(pa.string()),
        **{name: col[name] for name in ("temperature", "temperature_rate", "omega_norm", "alpha_norm")},
        **{name: _triples(vec[name]) for name in ("gravity", "predicted", "residual", "whitened")},
    })
    return schemas.stamp(table, "sample_residuals")


def _triples(x: np.ndarray) -> pa.FixedSizeListArray:
    """(n, 3) float64 as an Arrow column of 3-lists (no Python object per row)."""
    return pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(x, float).ravel()), 3)


def _last_power_on(t: np.ndarray, power_times: np.ndarray, t_all: np.ndarray) -> np.ndarray:
    starts = np.r_[t_all.min() if len(t_all) else 0.0, power_times]
    return starts[np.searchsorted(starts, t, "right") - 1]

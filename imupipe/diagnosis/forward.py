"""The calibrated model as a forward model of the whole recording, and its linearisation.

One module owns the physics of the nominal model of accelerometer and gyroscope
(``spec/effects.md``: ``y = S x + b0 + k (T - 25) + noise``) as it predicts a
recording made of rests and the motions between them, with every nuisance carried
as an unknown of the fit:

- **rests** -- each rest's mean accelerometer reading is ``S_a (g u_i) + b_a + k_a dT``
  with ``u_i`` the rest's unknown gravity direction (2 dof); its mean gyro reading is
  the gyro bias ``b_g + k_g dT``;
- **bias random walks** (gyro and accelerometer, ``imupipe.solvers.brownian``): the
  bias also wanders as a Wiener process; its states at every rest boundary are
  unknowns joined by independent increments (prior rows); a rest sees the walk's
  average over its interval, a motion its value interpolated across it. A rest that
  starts a new power cycle frees the walk (a new turn-on bias);
- **motions** -- the attitude is propagated from the rest before by the calibrated gyro
  (``attitude.py``). Its error is a Wiener process driven by the gyro's white noise;
  only its tilt matters for gravity, so it is carried as a 2-D Brownian path ``z(t)``
  (gnomonic coordinates of the gravity direction in the motion's start frame), pinned
  at the start by the rest before (``z_0 = delta_p``) and at the end by the rest after,
  with free knots in between (``knot_s`` apart) and independent increments as prior
  rows. With one knot interval this is the turn model of ``turn_model.py`` (the
  gravity carried through the turn against gravity measured after it); with knots,
  every accelerometer sample inside the motion is predicted and the path is
  conditioned on both ends (a Brownian bridge), so nothing is counted twice.

The rows (whitened: each block by its own noise) are named blocks with per-row
metadata (``Rows``): ``accel_rest``, ``gyro_rest``, ``motion_prior`` (the attitude
path's increments: the gyro's evidence in motion), ``accel_motion`` (every
accelerometer sample inside a motion), ``walk_gyro``/``walk_accel`` (the walks'
increments), ``k_prior`` (a thermal stage's k). The unknowns are the globals
``x_g`` (named column blocks, ``Globals``) and the locals ``x_l`` grouped in one
stage per rest (its direction, its walk states, the knots of the motion after it),
so the normal matrix is block-tridiagonal (``solvers/blocktri.py``) and every
evaluation, solve and leverage is linear in the recording's length.

Jacobians are analytic (checked against finite differences in
``tests/diagnosis/test_forward.py``). Frames: the instrument frame of the
accelerometer in the lower-triangular gauge (``S_a`` lower-triangular).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import SolverError
from ..models import T_REF_C
from ..observations import Rests, Turns
from ..rotations import skew
from ..solvers.triad_covariance import shape_basis
from .attitude import Attitude, MotionSamples, Points, Quadrature, RateDerivatives, by_motion

_LOWER = shape_basis("lower")  # (6, 3, 3)
SAMPLE_CHUNK = 8192  # motion samples whose derivatives are formed at once (memory, not speed)
GYRO_CHUNK = 12  # columns of a gyro term whose attitude sensitivities are formed at once (memory)
BLOCKS = ("accel_rest", "gyro_rest", "walk_gyro", "walk_accel", "turn", "accel_motion", "k_prior")
SENSOR_OF = {"accel_rest": "accel", "gyro_rest": "gyro", "turn": "gyro", "accel_motion": "accel",
             "walk_gyro": "gyro", "walk_accel": "accel", "k_prior": "prior"}
KIND_OF = {"accel_rest": "rest", "gyro_rest": "rest", "turn": "motion", "accel_motion": "motion",
           "walk_gyro": "prior", "walk_accel": "prior", "k_prior": "prior"}


def tangent_basis(u: np.ndarray) -> np.ndarray:
    """(n, 3, 2) orthonormal bases of the planes normal to unit vectors ``u`` (n, 3)."""
    helper = np.where(np.abs(u[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(u, e1)], axis=-1)


def _whiteners(cov: np.ndarray) -> np.ndarray:
    """(..., k, k) ``L^-1`` with ``L L^T = cov``."""
    return np.linalg.inv(np.linalg.cholesky(cov))


def _normalise(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (n, 3) and their derivative (n, 3, 3) w.r.t. ``v``: ``(I - u u^T) / |v|``
    (by ``SAMPLE_CHUNK`` rows: no whole-length temporaries beside the result)."""
    nv = np.linalg.norm(v, axis=1)
    u = v / nv[:, None]
    du = np.empty((len(v), 3, 3))
    for a in range(0, len(v), SAMPLE_CHUNK):
        c = slice(a, a + SAMPLE_CHUNK)
        np.divide(np.eye(3) - u[c, :, None] * u[c, None, :], nv[c, None, None], out=du[c])
    return u, du


# --------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class MotionAccel:
    """Accelerometer samples inside the motions: ``t`` (k,) s, ``y`` (k, 3) raw, ``motion`` (k,)
    the motion each belongs to (sorted by motion, then time)."""

    t: np.ndarray
    y: np.ndarray
    motion: np.ndarray

    @classmethod
    def select(cls, t: np.ndarray, y: np.ndarray, rests: Rests, turns: Turns) -> MotionAccel:
        """The samples of ``t``/``y`` strictly between each turn's two rests."""
        ts, ys, ms = [], [], []
        for j, (p, q) in enumerate(zip(turns.before, turns.after, strict=True)):
            i0 = np.searchsorted(t, rests.t_end_s[p], "right")
            i1 = np.searchsorted(t, rests.t_start_s[q], "left")
            ts.append(t[i0:i1])
            ys.append(y[i0:i1])
            ms.append(np.full(i1 - i0, j))
        if not ts:
            return cls(np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64))
        return cls(np.concatenate(ts), np.concatenate(ys), np.concatenate(ms).astype(np.int64))


@dataclass(frozen=True)
class Noise:
    """The recording's noise model: one raw sample's covariance per triad (3, 3) and the bias
    random-walk intensities (3,) per axis, (unit)^2/s (0: a constant bias)."""

    accel_sample: np.ndarray
    gyro_sample: np.ndarray
    q_accel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q_gyro: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def from_rests(cls, rests: Rests, q_accel=None, q_gyro=None) -> Noise:
        """White noise from the rests' median one-sample covariance (robust to a bad rest)."""
        return cls(np.median(rests.cov["accel"], axis=0), np.median(rests.cov["gyro"], axis=0),
                   np.zeros(3) if q_accel is None else np.broadcast_to(q_accel, 3).astype(float),
                   np.zeros(3) if q_gyro is None else np.broadcast_to(q_gyro, 3).astype(float))


@dataclass(frozen=True)
class Start:
    """The starting values of the nominal parameters (lower-triangular gauge) and the temperature
    coefficients' prior (``sigma_k`` (6,), inf where none)."""

    S_a: np.ndarray
    b_a: np.ndarray
    M_g: np.ndarray
    b_g: np.ndarray
    k_a: np.ndarray
    k_g: np.ndarray
    sigma_k: np.ndarray = field(default_factory=lambda: np.full(6, np.inf))


def rest_temperature(rests: Rests, temperature: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """(n,) degC: each rest's mean temperature (the regressor of a mean reading); from the
    temperature stream ``(t, T)`` when given (averaged over the rest), else the rests' own
    (``T_REF_C`` where they have none: no temperature term)."""
    if temperature is None or not len(temperature[0]):
        return np.where(np.isfinite(rests.temperature), rests.temperature, T_REF_C)
    t, T = temperature
    c = np.concatenate([[0.0], np.cumsum(T)])
    i0 = np.searchsorted(t, rests.t_start_s, "left")
    i1 = np.searchsorted(t, rests.t_end_s, "right")
    inside = i1 > i0
    mean = np.divide(c[i1] - c[i0], i1 - i0, out=np.zeros(len(rests)), where=inside)
    return np.where(inside, mean, np.interp(0.5 * (rests.t_start_s + rests.t_end_s), t, T))


# --------------------------------------------------------------------------- layout


@dataclass(frozen=True)
class Globals:
    """Named column blocks of ``x_g``: ``slices[name]``; ``size``."""

    slices: dict[str, slice]
    size: int

    @classmethod
    def build(cls, blocks: Sequence[tuple[str, int]]) -> Globals:
        out, o = {}, 0
        for name, n in blocks:
            out[name] = slice(o, o + n)
            o += n
        return cls(out, o)

    def names(self) -> list[str]:
        """One name per column, e.g. ``M_g[0,1]``, ``b_a[2]``."""
        out = []
        for name, s in self.slices.items():
            n = s.stop - s.start
            out += [f"{name}[{i}]" for i in range(n)]
        return out


@dataclass(frozen=True)
class Rows:
    """Metadata of every row of the whitened residual: ``block`` (N,) int8 index into ``BLOCKS``,
    ``index`` (N,) int32 the rest / motion / boundary / sample it belongs to, ``axis`` (N,) int8
    0-2 or -1, ``t`` (N,) s (the rest's or sample's time; the knot interval's middle)."""

    block: np.ndarray
    index: np.ndarray
    axis: np.ndarray
    t: np.ndarray

    def of(self, name: str) -> np.ndarray:
        return self.block == BLOCKS.index(name)

    @property
    def sensor(self) -> np.ndarray:
        return np.array([SENSOR_OF[BLOCKS[b]] for b in self.block])

    @property
    def kind(self) -> np.ndarray:
        return np.array([KIND_OF[BLOCKS[b]] for b in self.block])


class Stages:
    """Where each stage's locals sit in ``x_l``: per rest ``i``, its ``delta`` (2), the walk
    states at its start (unless ``pinned``) and end (3 each, per walk) and the free knots of
    the motion after it (2 each)."""

    def __init__(self, n: int, walks: Sequence[str], pinned: np.ndarray, knots: np.ndarray):
        sizes = 2 + 3 * len(walks) * 2 - 3 * len(walks) * pinned.astype(int) + 2 * np.asarray(knots, int)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.size = int(self.offsets[-1])
        first = self.offsets[:-1]
        self.delta = first[:, None] + np.arange(2)  # (n, 2) columns
        cursor = first + 2
        self.walk_cols: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # start (-1: pinned), end
        for w in walks:
            a = np.where(pinned, -1, cursor)
            cursor = cursor + np.where(pinned, 0, 3)
            self.walk_cols[w] = (a, cursor.copy())
            cursor = cursor + 3
        self.knot_start = cursor


# --------------------------------------------------------------------------- the model


class JointModel:
    """Forward model and whitened residuals of accelerometer + gyroscope over a recording.

    ``rests``/``turns``: the segmentation (turns join consecutive rests); ``gravity`` m/s^2;
    ``start``: starting values; ``noise``: the noise model; ``fit_k``: the temperature
    coefficients are unknowns (else the start's are applied); ``accel``: accelerometer samples
    inside the motions (per-sample mode) or None (rest means and turn end-points only);
    ``knot_s``: spacing of the attitude-error knots in per-sample mode; ``power_on`` (n,) bool:
    rest i starts a new power cycle (the walks restart free); ``temperature``: (t, T) arrays
    for temperatures inside motions (default: the rests' interpolated in time). ``like``: a
    model of the same rests and turns whose quadrature (and, for a subset of its motion
    samples, their integration weights) this one reuses.
    """

    def __init__(self, rests: Rests, turns: Turns, gravity: float, start: Start, noise: Noise,
                 fit_k: bool = False, accel: MotionAccel | None = None, knot_s: float = 0.25,
                 power_on: np.ndarray | None = None,
                 temperature: tuple[np.ndarray, np.ndarray] | None = None, like: JointModel | None = None):
        n, m = len(rests), len(turns)
        if n < 1:
            raise SolverError("the joint model needs at least one rest")
        if m and np.any(turns.after != turns.before + 1):
            raise SolverError("the joint model needs turns between consecutive rests")
        self.rests, self.turns, self.g, self.noise, self.fit_k = rests, turns, float(gravity), noise, fit_k
        self.n, self.m = n, m
        self.start = start
        self.sampled = accel is not None
        self.walks = [w for w, q in (("wg", noise.q_gyro), ("wa", noise.q_accel)) if np.any(q > 0)]
        self.q = {"wg": np.asarray(noise.q_gyro, float), "wa": np.asarray(noise.q_accel, float)}
        self.power_on = np.zeros(n, bool) if power_on is None else np.asarray(power_on, bool)
        pinned = np.zeros(n, bool)
        pinned[0] = True  # the walks' level is the bias itself
        self._temperature = temperature
        # ---- rests
        self.mid = 0.5 * (rests.t_start_s + rests.t_end_s)
        self.length = rests.t_end_s - rests.t_start_s
        self.dT = self.rest_temperature() - T_REF_C
        self.y_a, self.y_g = rests.need("accel"), rests.need("gyro")
        v0 = (self.y_a - np.outer(self.dT, start.k_a) - start.b_a) @ np.linalg.inv(start.S_a).T
        self.u0 = v0 / np.linalg.norm(v0, axis=1, keepdims=True)
        self.B = tangent_basis(self.u0)
        self.W_a = _whiteners(self.rest_cov(rests, "accel"))
        self.W_g = _whiteners(self.rest_cov(rests, "gyro"))
        # ---- motions
        if like is not None:
            self.motions, self.quad = like.motions, like.quad
        else:
            self.motions = MotionSamples.from_turns(turns.t, turns.gyro)
            self.quad = Quadrature(self.motions)
        ms = self.motions
        self.p, self.qr = np.asarray(turns.before, int), np.asarray(turns.after, int)
        self.dT_gyro = self.temperature_at(ms.t) - T_REF_C
        gap_start = rests.t_end_s[self.p] if m else np.zeros(0)
        gap_len = (rests.t_start_s[self.qr] - gap_start) if m else np.zeros(0)
        self.lam_gyro = self._walk_fraction(ms.t, ms.motion, gap_start, gap_len)
        self.accel = accel if accel is not None else MotionAccel(np.zeros(0), np.zeros((0, 3)),
                                                                 np.zeros(0, np.int64))
        self.dT_acc = self.temperature_at(self.accel.t) - T_REF_C
        self.accel_points = self._points(like)
        self.lam_acc = self._walk_fraction(self.accel.t, self.accel.motion, gap_start, gap_len)
        self.W_sample = _whiteners(noise.accel_sample)
        # ---- knots: (m,) intervals per motion, their times
        dur = np.where(np.isfinite(ms.end - ms.origin), ms.end - ms.origin, 0.0)
        self.K = np.ones(m, int) if not self.sampled else np.maximum(1, np.round(dur / knot_s)).astype(int)
        if self.sampled:
            has = np.bincount(self.accel.motion, minlength=m) > 0
            self.K = np.where(has, self.K, 1)
        knots_free = np.zeros(n, int)
        if m:
            knots_free[self.p] = self.K - 1
        self.stages = Stages(n, self.walks, pinned, knots_free)
        self.knot_t = [ms.origin[j] + (ms.end[j] - ms.origin[j]) * np.arange(self.K[j] + 1) / self.K[j]
                       for j in range(m)]
        # ---- globals
        blocks = [("S_a", 6), ("b_a", 3), ("M_g", 9), ("b_g", 3)]
        if fit_k:
            blocks += [("k_a", 3), ("k_g", 3)]
        self.glob = Globals.build(blocks)
        sk = np.asarray(start.sigma_k, float)
        self.k_prior = np.flatnonzero(np.isfinite(sk) & (sk > 0)) if fit_k else np.zeros(0, int)
        self.k_prior_w = 1.0 / sk[self.k_prior]
        self.k0 = np.concatenate([start.k_a, start.k_g])
        self.x_g0 = np.concatenate([start.S_a[np.tril_indices(3)], start.b_a, start.M_g.ravel(), start.b_g,
                                    *([start.k_a, start.k_g] if fit_k else [])])
        # the attitude-error increments' covariance, fixed at the start (one quadratic form)
        self.Qk_w = self._knot_whiteners()
        self.x_l0 = self._initial_locals()
        self.rows = self._rows()

    # ------------------------------------------------------------------ helpers
    def _points(self, like: JointModel | None) -> Points:
        """The motion samples' integration weights; a subset of ``like``'s rows when its samples
        hold ours (the weights are computed row by row, so the subset is exact)."""
        acc = self.accel
        if like is not None and len(acc.t) <= len(like.accel.t):
            key = like.accel.motion * 1e9 + like.accel.t  # motions, then times: sorted
            idx = np.searchsorted(key, acc.motion * 1e9 + acc.t)
            idx = np.minimum(idx, max(len(key) - 1, 0))
            if len(key) and np.array_equal(like.accel.t[idx], acc.t) and \
                    np.array_equal(like.accel.motion[idx], acc.motion):
                return like.accel_points.subset(idx)
        return self.quad.points(acc.t, acc.motion)

    def rest_cov(self, rests: Rests, sensor: str) -> np.ndarray:
        """(n, 3, 3) covariance of each rest's mean reading about the model's: the samples'
        noise averaged, plus the bias walk's wander about its mean over the rest (a Brownian
        bridge: q T / 12)."""
        bridge = np.outer(self.length / 12.0, self.q["wa" if sensor == "accel" else "wg"])
        return rests.cov_of_mean(sensor) + bridge[:, :, None] * np.eye(3)

    def temperature_at(self, t: np.ndarray) -> np.ndarray:
        """degC at times ``t`` (s): the temperature stream when given, else the rests' means
        interpolated in time; unknown is the reference (no thermal term)."""
        t = np.asarray(t, float)
        if self._temperature is not None and len(self._temperature[0]):
            return np.interp(t, *self._temperature)
        T = self.rests.temperature
        ok = np.isfinite(T)
        if not ok.any():
            return np.full(t.shape, T_REF_C)
        return np.interp(t, self.mid[ok], T[ok])

    def rest_temperature(self) -> np.ndarray:
        """(n,) degC: each rest's mean temperature (``rest_temperature``)."""
        return rest_temperature(self.rests, self._temperature)

    def accel_prediction(self, P: dict, f: np.ndarray, t: np.ndarray,
                         walk: np.ndarray | None = None) -> np.ndarray:
        """Raw accelerometer readings (k, 3) for specific force ``f`` (k, 3) at times ``t`` (k,):
        ``S_a f + b_a + k_a (T(t) - 25) + walk``."""
        pred = f @ P["S_a"].T + P["b_a"] + np.outer(self.temperature_at(t) - T_REF_C, P["k_a"])
        return pred if walk is None else pred + walk

    def _walk_fraction(self, t, motion, gap_start, gap_len) -> np.ndarray:
        if not len(t):
            return np.zeros(0)
        gl = gap_len[motion]
        return np.clip(np.divide(t - gap_start[motion], gl, out=np.full(len(t), 0.5), where=gl > 0), 0, 1)

    def unpack(self, x_g: np.ndarray) -> dict[str, np.ndarray]:
        s = self.glob.slices
        S_a = np.zeros((3, 3))
        S_a[np.tril_indices(3)] = x_g[s["S_a"]]
        out = {"S_a": S_a, "b_a": x_g[s["b_a"]], "M_g": x_g[s["M_g"]].reshape(3, 3), "b_g": x_g[s["b_g"]]}
        out["k_a"] = x_g[s["k_a"]] if self.fit_k else self.start.k_a
        out["k_g"] = x_g[s["k_g"]] if self.fit_k else self.start.k_g
        return out

    def walk_states(self, x_l: np.ndarray, w: str) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) the walk ``w`` at each rest's start and end (zeros when pinned/absent)."""
        if w not in self.walks:
            return np.zeros((self.n, 3)), np.zeros((self.n, 3))
        a, b = self.stages.walk_cols[w]
        A = np.where(a[:, None] >= 0, x_l[np.maximum(a, 0)[:, None] + np.arange(3)], 0.0)
        B = x_l[b[:, None] + np.arange(3)]
        return A, B

    def gravity(self, x_l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) unit gravity at each rest and (n, 3, 2) its derivative w.r.t. ``delta``."""
        d = x_l[self.stages.delta]
        u, du = _normalise(self.u0 + np.einsum("nij,nj->ni", self.B, d))
        return u, du @ self.B

    def _rates(self, P: dict, x_l: np.ndarray, derivatives: bool = True) -> tuple[np.ndarray, RateDerivatives | None]:
        """Calibrated rates (N, 3) of the motions' gyro samples and their derivatives (N, 3, 21)
        w.r.t. (M_g (9), b_g (3), k_g (3), walk at the motion's start (3), at its end (3)),
        factored (``attitude.RateDerivatives``); ``derivatives=False``: None for them."""
        ms = self.motions
        N = len(ms)
        wa, wb = self.walk_states(x_l, "wg")
        j = ms.motion
        lam = self.lam_gyro[:, None]
        # (N, 3) arrays formed in place (the same operations in the same order), e in the
        # derivatives' first columns: this is the refine stage's peak (3.6 MiB each at 1 h)
        coef = np.empty((N, 7 if derivatives else 3))
        e = coef[:, :3]
        np.subtract(ms.y, P["b_g"], out=e)
        e -= np.outer(self.dT_gyro, P["k_g"])
        if N:
            walk = wb[self.p[j]]
            walk *= 1 - lam
            end = wa[self.qr[j]]
            end *= lam
            walk += end
            del end
            e -= walk
            del walk
        omega = e @ P["M_g"].T
        if not derivatives:
            return omega, None
        # d omega / d M_g[i, c] = e_c along axis i; the rest is -M_g times 1, dT, 1 - lam, lam
        basis = np.zeros((7, 3, 21))
        for c in range(3):
            basis[c, np.arange(3), 3 * np.arange(3) + c] = 1.0
        for b in range(4):
            basis[3 + b, :, 9 + 3 * b:12 + 3 * b] = -P["M_g"]
        coef[:, 3] = 1.0
        coef[:, 4] = self.dT_gyro
        coef[:, 5] = 1 - lam[:, 0]
        coef[:, 6] = lam[:, 0]
        return omega, RateDerivatives(coef, basis)

    def _knot_whiteners(self) -> list[np.ndarray]:
        """Per motion, (K_j, 2, 2) whiteners of the attitude-path increments: the gyro's white noise
        integrated over each knot interval, tilt part in the start rest's tangent plane, plus the
        gyro walk's wander about its interpolation across the motion (``q T^3 / 12`` in all)."""
        P = self.unpack(self.x_g0)
        omega, _ = self._rates(P, self.x_l0_zero(), derivatives=False)
        att = Attitude.integrate(self.quad, omega)
        ms = self.motions
        Sg = P["M_g"] @ self.noise.gyro_sample @ P["M_g"].T
        # sample s's white noise turns the attitude by its quadrature weight times the rate error,
        # in the frame of the attitude at the sample
        wq = np.asarray(self.quad.A.sum(axis=0)).ravel() if len(ms) else np.zeros(0)
        step, steps = self.quad.step, by_motion(self.quad.seg, self.m)
        out = []
        qg = float(np.mean(self.q["wg"])) if "wg" in self.walks else 0.0
        for j, sel in enumerate(by_motion(ms.motion, self.m)):
            K = self.K[j]
            k = np.clip(np.searchsorted(self.knot_t[j], ms.t[sel], "right") - 1, 0, K - 1)
            # each sample's attitude: before its step, the motion's whole turn at its last sample
            # (motion by motion: no (N, 3, 3) arrays)
            R = np.tile(np.eye(3), (sel.stop - sel.start, 1, 1))
            s = steps[j]
            if s.stop > s.start:
                R[step[s] - sel.start] = att.rotations_before(s)
                R[step[s.stop - 1] + 1 - sel.start] = att.total[j]
            Phi = np.zeros((K, 3, 3))
            np.add.at(Phi, k, wq[sel, None, None] ** 2 * (R @ Sg @ np.swapaxes(R, 1, 2)))
            T = ms.end[j] - ms.origin[j] if np.isfinite(ms.end[j]) else 0.0
            if qg and T > 0:
                Phi += qg * T**3 / 12.0 / K * (P["M_g"] @ P["M_g"].T)
            p = self.p[j]
            X = skew(self.u0[p]) @ self.B[p]  # tilt of gravity per unit rotation, in-plane
            Q = X.T @ Phi @ X + 1e-30 * np.eye(2)
            # in gnomonic coordinates at u0_p, d z = B^T (phi x u0) = -(X^T phi) up to sign
            out.append(_whiteners(Q))
        return out

    def x_l0_zero(self) -> np.ndarray:
        return np.zeros(self.stages.size)

    def _initial_locals(self) -> np.ndarray:
        """Zero directions and walks; interior knots on the line between the end-points."""
        x = np.zeros(self.stages.size)
        if not self.m or not self.sampled:
            return x
        zK = self._endpoints(self.unpack(self.x_g0), x, jacobian=False)[0]
        for j in range(self.m):
            K = self.K[j]
            if K > 1:
                frac = np.arange(1, K) / K
                x[self.stages.knot_start[self.p[j]] + np.arange(2 * (K - 1))] = np.outer(frac, zK[j]).ravel()
        return x

    def _endpoints(self, P: dict, x_l: np.ndarray, jacobian: bool = True, with_globals: bool = True,
                   rate_columns: np.ndarray | None = None, att: Attitude | None = None):
        """Gnomonic end-point ``z_K`` (m, 2) of every motion and what it needs for derivatives
        (``jacobian=False``: None for ``dz_gyro``, ``dz_dq`` and ``D``; ``with_globals=False``:
        the rate derivatives and ``dz_gyro`` hold the 6 walk columns only; ``rate_columns``
        (N_g, 3, k): the derivatives of the motions' calibrated rates w.r.t. k other parameters, in
        place of the model's own (``gyro_columns``), with ``att`` the attitude at ``P``, ``x_l``)."""
        if rate_columns is not None:
            omega, D = att.omega, rate_columns
        else:
            omega, D = self._rates(P, x_l, derivatives=jacobian)
            if D is not None and not with_globals:
                D = RateDerivatives(D.coef, D.basis[:, :, 15:])
            att = Attitude.integrate(self.quad, omega)
            omega = att.omega  # the same numbers; when the attitude is the one kept, its rates alone
        u, du = self.gravity(x_l)
        w = np.einsum("mij,mj->mi", att.total, u[self.qr]) if self.m else np.zeros((0, 3))
        u0p, Bp = self.u0[self.p], self.B[self.p]
        den = np.einsum("mi,mi->m", u0p, w)
        zK = np.einsum("mia,mi->ma", Bp, w) / den[:, None]
        if not jacobian:
            return zK, None, None, att, None, omega, u, du
        G = (np.swapaxes(Bp, 1, 2) - np.einsum("ma,mi->mai", zK, u0p)) / den[:, None, None]  # dz/dw
        # the motion samples' rows form the sums before their steps by chunks of samples
        # (Attitude.sensitivity): no (S, 3, 21) array through the fit
        phi_T = att.end_sensitivity(D)  # (m, 3, 21)
        dz_gyro = np.einsum("mai,mij,mjp->map", G, -skew(w), phi_T)  # (m, 2, 21)
        dz_dq = np.einsum("mai,mij,mjk->mak", G, att.total, du[self.qr])  # (m, 2, 2)
        return zK, dz_gyro, dz_dq, att, D, omega, u, du

    @property
    def has_samples(self) -> bool:
        """Whether the motions' accelerometer samples have rows (their attitude's sensitivities)."""
        return bool(self.sampled and len(self.accel.t))

    @property
    def motion_rows(self) -> np.ndarray:
        """The rows a term on the motions' gyro samples moves: the turns', then the motion samples'."""
        return np.flatnonzero(self.rows.of("turn") | self.rows.of("accel_motion"))

    def gyro_columns(self, x_g: np.ndarray, x_l: np.ndarray, dy: np.ndarray | RateDerivatives,
                     negate: bool = False) -> GyroColumns:
        """(len(motion_rows), k) d r / d theta on the ``motion_rows`` of a term ``dy`` (N_g, 3, k)
        added to the motions' raw gyro samples (zero on every other row), analytically: the
        calibration turns it into rate derivatives ``M_g dy``, which move the attitude at the
        motions' samples and end-points. ``dy`` may come factored (``RateDerivatives``: a few
        signals times a basis), as a library's columns do: no (N_g, 3, k) array then. Formed by
        slices of rows when indexed (``GyroColumns``; ``[:]``: all of them); ``negate``: minus them."""
        return GyroColumns(self, x_g, x_l, dy, negate)

    def turn_view(self, x_g: np.ndarray, x_l: np.ndarray) -> dict[str, np.ndarray]:
        """Per motion, in the body frame at its end (gauge frame): ``predicted`` (m, 3) the rest
        before's gravity carried through the calibrated motion, ``measured`` (m, 3) the rest
        after's, ``rotation`` (m, 3, 3), ``sigma_gyro`` (m,) rad, the RMS 1-sigma per component
        of the attitude error the gyro's noise leaves at the end."""
        P = self.unpack(x_g)
        omega, _ = self._rates(P, x_l, derivatives=False)
        R = Attitude.integrate(self.quad, omega).total
        u = self.gravity(x_l)[0]
        pred = np.einsum("mji,mj->mi", R, u[self.p]) if self.m else np.zeros((0, 3))
        sig = []
        for W in self.Qk_w:
            Q = sum(np.linalg.inv(w.T @ w) for w in W)  # increments' covariances add up
            sig.append(np.sqrt(np.trace(Q) / 2))
        return {"predicted": pred, "measured": u[self.qr], "rotation": R, "sigma_gyro": np.array(sig)}

    # ------------------------------------------------------------------ rows
    def _rows(self) -> Rows:
        n, m = self.n, self.m
        parts = []

        def add(block: str, index, axis, t) -> None:
            index = np.asarray(index)
            parts.append((np.full(len(index), BLOCKS.index(block)), index, np.asarray(axis), np.asarray(t)))

        ax = np.tile(np.arange(3), n)
        add("accel_rest", np.repeat(np.arange(n), 3), ax, np.repeat(self.mid, 3))
        add("gyro_rest", np.repeat(np.arange(n), 3), ax, np.repeat(self.mid, 3))
        for w, name in (("wg", "walk_gyro"), ("wa", "walk_accel")):
            if w in self.walks:
                pairs = self._walk_pairs(w)
                add(name, np.repeat(np.arange(len(pairs[0])), 3), np.tile(np.arange(3), len(pairs[0])),
                    np.repeat(pairs[3], 3))
        idx, tt = [], []
        for j in range(m):
            kt = self.knot_t[j]
            idx.append(np.repeat(np.full(self.K[j], j), 2))
            tt.append(np.repeat(0.5 * (kt[1:] + kt[:-1]), 2))
        if m:
            add("turn", np.concatenate(idx), np.full(2 * self.K.sum(), -1), np.concatenate(tt))
        if self.sampled and len(self.accel.t):
            k = len(self.accel.t)
            add("accel_motion", np.repeat(np.arange(k), 3), np.tile(np.arange(3), k),
                np.repeat(self.accel.t, 3))
        if len(self.k_prior):
            add("k_prior", self.k_prior, np.full(len(self.k_prior), -1), np.full(len(self.k_prior), np.nan))
        block, index, axis, t = (np.concatenate([p[i] for p in parts]) for i in range(4))
        # labels in narrow types: held through the whole map (7 bytes a row instead of 24, and t)
        return Rows(block.astype(np.int8), index.astype(np.int32), axis.astype(np.int8), t.astype(float))

    def _walk_pairs(self, w: str):
        """Consecutive walk states: (prev column or -1 pinned, next column, dt (s), midpoint time)."""
        a, b = self.stages.walk_cols[w]
        prev, nxt, dts, mids = [], [], [], []
        rs = self.rests
        for i in range(self.n):
            if i > 0 and not self.power_on[i]:
                prev.append(b[i - 1])
                nxt.append(a[i])
                dts.append(rs.t_start_s[i] - rs.t_end_s[i - 1])
                mids.append(0.5 * (rs.t_start_s[i] + rs.t_end_s[i - 1]))
            prev.append(a[i])
            nxt.append(b[i])
            dts.append(self.length[i])
            mids.append(self.mid[i])
        return np.array(prev), np.array(nxt), np.maximum(np.array(dts), 1e-9), np.array(mids)

    # ------------------------------------------------------------------ residuals
    def residuals(self, x_g: np.ndarray, x_l: np.ndarray, signals: bool = False, jacobian: bool = True,
                  with_globals: bool = True, out: tuple | None = None):
        """Whitened residual ``r`` (N,), ``J_g`` (N, P_g) dense, ``J_l`` (N, P_l) CSR; with
        ``signals`` also a dict of the model's intermediate quantities (predictions, gravity);
        ``jacobian=False``: the residual alone (None for both Jacobians, far cheaper);
        ``with_globals=False``: ``J_g`` has no columns (a fit of the nuisances alone); ``out``:
        ``(J_g, J_l)`` of an earlier evaluation the caller gives up, written over where they fit
        (no fresh memory per step of a fit)."""
        P = self.unpack(x_g)
        n, g, gl = self.n, self.g, self.glob.slices
        Pg, Pl = self.glob.size, self.stages.size
        S_a = P["S_a"]
        r_parts, trip = [], []
        row0 = 0
        N = len(self.rows.block)
        old_g, old_l = out if out is not None else (None, None)
        # J_l's values go straight to their CSR places once the model knows its sparsity
        pattern = self.__dict__.get("_jl_pattern") if jacobian else None
        data = None
        if pattern is not None:
            same = old_l is not None and old_l.shape == (N, Pl) and old_l.nnz == len(pattern[0])
            data = old_l.data if same else np.empty(len(pattern[0]))
        filled = 0
        # the globals' Jacobian is written in place, block by block (no stacked copy)
        J_g = None
        if jacobian:
            shape = (N, Pg if with_globals else 0)
            J_g = old_g if old_g is not None and old_g.shape == shape else np.zeros(shape)
            if J_g is old_g:
                J_g.fill(0.0)

        def block(r: np.ndarray, Jg: np.ndarray | None) -> int:
            """Append rows ``r`` and their ``Jg`` (None: zero, or already written through
            ``block.reserve``); returns their first row."""
            nonlocal row0
            r_parts.append(r)
            if jacobian and with_globals and Jg is not None:
                J_g[row0:row0 + len(r)] = Jg
            start = row0
            row0 += len(r)
            return start

        block.reserve = lambda n: J_g[row0:row0 + n]  # the next n rows' J_g, to fill in place
        block.globals = with_globals

        def put(vals: np.ndarray) -> None:
            nonlocal filled
            data[pattern[0][filled:filled + len(vals)]] = vals
            filled += len(vals)

        def local(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray) -> None:
            if not jacobian:
                return
            keep = cols >= 0
            if data is not None:
                put(vals[keep].ravel())
            else:
                trip.append((rows[keep].ravel(), cols[keep].ravel(), vals[keep].ravel()))

        def flat(where, vals: np.ndarray, span: tuple[int, int]) -> None:
            """Entries ``vals`` (kept ones only) whose rows and columns ``where()`` returns (a
            constant pattern: asked for only until the model knows J_l's sparsity), on rows
            ``span`` (first, last) at most."""
            if data is not None:
                put(vals)
            elif jacobian:
                trip.append((where, span, vals))

        local.flat = flat

        zK, dz_gyro, dz_dq, att, D, omega, u, du = self._endpoints(P, x_l, jacobian, with_globals) if self.m else \
            (None,) * 6 + self.gravity(x_l)
        wga, wgb = self.walk_states(x_l, "wg")
        waa, wab = self.walk_states(x_l, "wa")
        # ---- accel rests
        pred_a = g * u @ S_a.T + P["b_a"] + np.outer(self.dT, P["k_a"]) + 0.5 * (waa + wab)
        r = np.einsum("nij,nj->ni", self.W_a, self.y_a - pred_a)
        Jg = np.zeros((n, 3, Pg))
        Jg[:, :, gl["S_a"]] = -g * np.einsum("nij,kjl,nl->nik", self.W_a, _LOWER, u)
        Jg[:, :, gl["b_a"]] = -self.W_a
        if self.fit_k:
            Jg[:, :, gl["k_a"]] = -self.W_a * self.dT[:, None, None]
        s0 = block(r.ravel(), Jg.reshape(3 * n, Pg))
        rows3 = s0 + 3 * np.arange(n)[:, None] + np.arange(3)  # (n, 3)
        blk = -g * np.einsum("nij,jk,nkl->nil", self.W_a, S_a, du)  # (n, 3, 2)
        local(np.repeat(rows3[:, :, None], 2, 2), np.repeat(self.stages.delta[:, None, :], 3, 1), blk)
        if "wa" in self.walks:
            a, b = self.stages.walk_cols["wa"]
            for cols in (a, b):
                cc = np.where(cols[:, None, None] >= 0, cols[:, None, None] + np.arange(3)[None, None, :], -1)
                local(np.repeat(rows3[:, :, None], 3, 2), np.repeat(cc, 3, 1), -0.5 * self.W_a)
        # ---- gyro rests
        pred_g = P["b_g"] + np.outer(self.dT, P["k_g"]) + 0.5 * (wga + wgb)
        r = np.einsum("nij,nj->ni", self.W_g, self.y_g - pred_g)
        Jg = np.zeros((n, 3, Pg))
        Jg[:, :, gl["b_g"]] = -self.W_g
        if self.fit_k:
            Jg[:, :, gl["k_g"]] = -self.W_g * self.dT[:, None, None]
        s0 = block(r.ravel(), Jg.reshape(3 * n, Pg))
        rows3 = s0 + 3 * np.arange(n)[:, None] + np.arange(3)
        if "wg" in self.walks:
            a, b = self.stages.walk_cols["wg"]
            for cols in (a, b):
                cc = np.where(cols[:, None, None] >= 0, cols[:, None, None] + np.arange(3)[None, None, :], -1)
                local(np.repeat(rows3[:, :, None], 3, 2), np.repeat(cc, 3, 1), -0.5 * self.W_g)
        # ---- walk increments
        for w in self.walks:
            prev, nxt, dts, _ = self._walk_pairs(w)
            k = len(prev)
            sq = np.sqrt(self.q[w][None, :] * dts[:, None])  # (k, 3)
            xn = x_l[nxt[:, None] + np.arange(3)]
            xp = np.where(prev[:, None] >= 0, x_l[np.maximum(prev, 0)[:, None] + np.arange(3)], 0.0)
            s0 = block(((xn - xp) / sq).ravel(), None)
            rows = s0 + 3 * np.arange(k)[:, None] + np.arange(3)
            local(rows, nxt[:, None] + np.arange(3), 1.0 / sq)
            local(rows, np.where(prev[:, None] >= 0, prev[:, None] + np.arange(3), -1), -1.0 / sq)
        sig = {"pred_accel_rest": pred_a, "pred_gyro_rest": pred_g, "gravity_rest": u}
        if self.m:
            self._motion_rows(P, x_l, zK, dz_gyro, dz_dq, att, D, omega, u, du, block, local, sig, jacobian)
        del att, D  # the attitude's sensitivities: not needed past the motions' rows
        # ---- temperature-coefficient prior
        if len(self.k_prior):
            k_all = np.concatenate([P["k_a"], P["k_g"]])
            Jg = np.zeros((len(self.k_prior), Pg))
            ks = gl["k_a"].start
            Jg[np.arange(len(self.k_prior)), ks + self.k_prior] = self.k_prior_w
            block((k_all - self.k0)[self.k_prior] * self.k_prior_w, Jg)
        r = np.concatenate(r_parts)
        if not jacobian:
            return (r, None, None, sig) if signals else (r, None, None)
        if len(r) != len(J_g):
            raise AssertionError("row metadata and residual rows disagree")
        if data is None:
            J_l = self._local_jacobian(trip, len(r), Pl)
        elif filled != len(data):
            raise AssertionError("J_l's entries and its sparsity pattern disagree")
        else:
            J_l = sp.csr_matrix((data, *pattern[1:]), shape=(len(r), Pl))
        return (r, J_g, J_l, sig) if signals else (r, J_g, J_l)

    def forget_jacobian_places(self) -> None:
        """Drop where J_l's values go (one integer per entry), kept to form Jacobians again: after
        the model's last fit they would only raise the later peak (a next Jacobian sorts again)."""
        self.__dict__.pop("_jl_pattern", None)

    def _local_jacobian(self, trip: list, N: int, Pl: int) -> sp.csr_matrix:
        """J_l (N, Pl) CSR from its entries ``trip`` (rows, columns, values; a constant pattern
        may come as (``where``, ``span``, values): ``where()`` gives its rows and columns when
        asked, ``span`` its first and last row, or None). Its sparsity does not change between
        evaluations: this first one sorts the entries into CSR order and keeps each entry's place
        (when no entry repeats a row and column), where later evaluations write their values
        (``residuals``). The sources are sorted in groups whose rows overlap (a motion's turn
        rows, a chunk of motion samples, the rests'); groups on disjoint rows follow each other
        in CSR order, so no sort key or order is ever as long as J_l, and each source's values
        are let go once placed."""
        sizes = np.array([len(t[2]) for t in trip], np.int64)
        starts = np.r_[0, np.cumsum(sizes)]
        nnz, width = int(starts[-1]), max(Pl, 1)
        idx = np.int32 if max(N, Pl, nnz) < 2**31 else np.int64

        def entries(i: int) -> tuple[np.ndarray, np.ndarray]:
            rr, cc, _ = trip[i]
            return rr() if callable(rr) else (rr, cc)

        present = np.flatnonzero(sizes)
        spans = np.empty((len(present), 2), np.int64)
        for n, i in enumerate(present):
            rr, cc, _ = trip[i]
            rows = np.asarray(cc) if callable(rr) and cc is not None else entries(i)[0]
            spans[n] = rows.min(), rows.max()
        groups, last = [], -1
        for n in np.argsort(spans[:, 0], kind="stable"):
            first_row, last_row = (int(x) for x in spans[n])
            if groups and first_row <= last:  # overlaps the group before: sorted with it
                groups[-1].append(int(present[n]))
                last = max(last, last_row)
            else:
                groups.append([int(present[n])])
                last = last_row
        indices, counts, place = np.empty(nnz, idx), np.zeros(N, np.int64), np.empty(nnz, idx)
        pos = 0
        for group in groups:
            group.sort()  # in source order: the stable sort keeps a repeat's entries in it
            key = np.concatenate([np.multiply(r, width, dtype=np.int64) + c for r, c in map(entries, group)])
            order = np.argsort(key, kind="stable")  # row-major: each row's entries in column order
            key = key[order]
            if np.any(key[1:] == key[:-1]):  # repeats add up
                rows, cols = (np.concatenate(x) for x in zip(*map(entries, range(len(trip))), strict=True))
                return sp.csr_matrix((np.concatenate([t[2] for t in trip]), (rows, cols)), shape=(N, Pl))
            n = len(key)
            row, indices[pos:pos + n] = np.divmod(key, width)  # one integer division for both
            first = int(row[0])
            counts[first:int(row[-1]) + 1] += np.bincount(row - first)
            source = np.concatenate([np.arange(starts[i], starts[i + 1]) for i in group])
            place[source[order]] = np.arange(pos, pos + n, dtype=idx)
            pos += n
        indptr = np.r_[0, np.cumsum(counts)].astype(idx)
        data = np.empty(nnz)
        for i in range(len(trip)):
            data[place[starts[i]:starts[i + 1]]] = trip[i][2]
            trip[i] = None
        self.__dict__["_jl_pattern"] = (place, indices, indptr)
        return sp.csr_matrix((data, indices, indptr), shape=(N, Pl))

    def _gyro_cols(self, j: np.ndarray) -> tuple[list[tuple[str | None, np.ndarray]], np.ndarray]:
        """Where the 21 rate-derivative columns of motions ``j`` go: globals M_g, b_g, [k_g], and
        the gyro walk's local columns at the motion's start and end (-1: pinned/absent)."""
        gl = self.glob.slices
        cols_g = np.r_[np.arange(gl["M_g"].start, gl["M_g"].stop), np.arange(gl["b_g"].start, gl["b_g"].stop),
                       np.arange(gl["k_g"].start, gl["k_g"].stop) if self.fit_k else np.full(3, -1)]
        if "wg" in self.walks:
            a, b = self.stages.walk_cols["wg"]
            wb = b[self.p[j]][:, None] + np.arange(3)
            wa = np.where(a[self.qr[j]][:, None] >= 0, a[self.qr[j]][:, None] + np.arange(3), -1)
            cols_l = np.hstack([wb, wa])
        else:
            cols_l = np.full((len(j), 6), -1)
        return cols_g, cols_l

    def _motion_rows(self, P, x_l, zK, dz_gyro, dz_dq, att, D, omega, u, du, block, local, sig,
                     jac: bool = True) -> None:
        m, Pg = self.m, self.glob.size
        cols_g, cols_l = self._gyro_cols(np.arange(m))
        gsel = cols_g >= 0
        # ---- attitude-path increments (prior rows): z_0 = delta_p, free interior knots, z_K
        for j in range(m):
            K, p, q = self.K[j], self.p[j], self.qr[j]
            ks = self.stages.knot_start[p]
            interior = x_l[ks:ks + 2 * (K - 1)].reshape(K - 1, 2)
            z = np.vstack([x_l[self.stages.delta[p]], interior, zK[j]])
            W = self.Qk_w[j]  # (K, 2, 2)
            r = np.einsum("kab,kb->ka", W, z[1:] - z[:-1])
            if not jac:
                block(r.ravel(), None)
                continue
            if block.globals:
                Jg = np.zeros((K, 2, Pg))
                Jg[-1][:, cols_g[gsel]] = (W[-1] @ dz_gyro[j])[:, :15][:, gsel]
                s0 = block(r.ravel(), Jg.reshape(2 * K, Pg))
            else:
                s0 = block(r.ravel(), None)
            rows = s0 + 2 * np.arange(K)[:, None] + np.arange(2)  # (K, 2)
            knot_cols = np.vstack([self.stages.delta[p], ks + np.arange(2 * (K - 1)).reshape(K - 1, 2),
                                   np.full((1, 2), -2)])  # -2: the end-point (a function)
            for side, sgn in ((slice(1, None), 1.0), (slice(None, -1), -1.0)):
                kc = knot_cols[side]  # (K, 2) columns of z_{k+1} (sgn +) or z_k (sgn -)
                real = kc[:, 0] >= 0
                if real.any():
                    local(np.repeat(rows[real][:, :, None], 2, 2), np.repeat(kc[real][:, None, :], 2, 1),
                          sgn * W[real])
            Wl = W[-1]
            local(np.repeat(rows[-1][:, None], 2, 1), np.repeat(self.stages.delta[q][None, :], 2, 0),
                  Wl @ dz_dq[j])
            local(np.repeat(rows[-1][:, None], 6, 1), np.repeat(cols_l[j][None, :], 2, 0),
                  (Wl @ dz_gyro[j])[:, -6:])
        if not self.has_samples:
            return
        self._sample_rows(P, x_l, zK, dz_gyro, dz_dq, att, D, u, block, local, sig, cols_g, jac)

    def _sample_layout(self) -> dict[str, np.ndarray]:
        """What the motion samples' rows need that does not change between evaluations (kept):
        each sample's knot interval ``kidx`` and weight ``mu``, those on their motion's last
        interval (``last``), and which of their rows' 16 entries exist (``keep``)."""
        lay = self.__dict__.get("_layout")
        if lay is not None:
            return lay
        acc = self.accel
        k = len(acc.t)
        j = acc.motion
        kidx = np.zeros(k, int)
        mu = np.zeros(k)
        for jj, sel in enumerate(by_motion(j, self.m)):
            if sel.stop == sel.start:
                continue
            kt = self.knot_t[jj]
            ki = np.clip(np.searchsorted(kt, acc.t[sel], "right") - 1, 0, self.K[jj] - 1)
            kidx[sel] = ki
            mu[sel] = np.clip((acc.t[sel] - kt[ki]) / (kt[ki + 1] - kt[ki]), 0, 1)
        last = kidx + 1 == self.K[j]  # the knot after is the end-point, a function of the next rest's direction
        lay = {"kidx": kidx, "mu": mu, "last": last}
        lay["keep"] = np.broadcast_to((self._sample_columns(lay) >= 0)[:, None, :], (k, 3, 16))
        self.__dict__["_layout"] = lay
        return lay

    def _sample_columns(self, lay: dict[str, np.ndarray]) -> np.ndarray:
        """The local columns (k, 16) of the motion samples' rows' entries: the knot (or rest
        direction) before and after each sample (2 each), the gyro walk at its motion's ends (6),
        the accelerometer walk at them (6); -1 for none. Not kept: J_l's sparsity needs them once."""
        j = self.accel.motion
        p, q = self.p[j], self.qr[j]
        kidx, last = lay["kidx"], lay["last"]
        ks = self.stages.knot_start[p]
        delta = self.stages.delta
        cols = np.full((len(j), 16), -1, np.int64)
        cols[:, 0:2] = np.where((kidx == 0)[:, None], delta[p], (ks + 2 * (kidx - 1))[:, None] + np.arange(2))
        cols[:, 2:4] = np.where(last[:, None], delta[q], (ks + 2 * kidx)[:, None] + np.arange(2))
        cols[:, 4:10] = self._gyro_cols(np.arange(self.m))[1][j]
        if "wa" in self.walks:
            a, b = self.stages.walk_cols["wa"]
            cols[:, 10:13] = b[p][:, None] + np.arange(3)
            cols[:, 13:16] = np.where(a[q][:, None] >= 0, a[q][:, None] + np.arange(3), -1)
        return cols

    def _sample_geometry(self, P: dict, x_l: np.ndarray, zK: np.ndarray, att: Attitude, c: slice
                         ) -> dict[str, np.ndarray]:
        """Where the gravity of motion samples ``c`` (a slice: the whole-length arrays would raise
        every evaluation's peak) comes from: their rotation ``R`` (k, 3, 3) from the motion's
        start, the start-frame direction ``nvec`` (k, 3) of the gnomonic point interpolated
        between its knots (weight ``mu``; ``last``: on the motion's last interval) and its
        derivative ``dn`` (k, 3, 3), the point's basis ``Bp`` (k, 3, 2); ``WS`` (3, 3) the
        whitened residual's derivative w.r.t. gravity in the body."""
        j = self.accel.motion[c]
        k = len(j)
        p = self.p[j]
        lay = self._sample_layout()
        kidx, mu = lay["kidx"][c], lay["mu"][c]
        Kj = self.K[j]
        ks = self.stages.knot_start[p]

        def knot_value(idx: np.ndarray) -> np.ndarray:
            out = np.empty((k, 2))
            first, last = idx == 0, idx == Kj
            mid = ~first & ~last
            out[first] = x_l[self.stages.delta[p[first]]]
            out[last] = zK[j[last]]
            out[mid] = x_l[(ks[mid] + 2 * (idx[mid] - 1))[:, None] + np.arange(2)]
            return out

        z = (1 - mu)[:, None] * knot_value(kidx) + mu[:, None] * knot_value(kidx + 1)
        Bp = self.B[p]
        nvec, dn = _normalise(self.u0[p] + (Bp @ z[:, :, None])[:, :, 0])
        return {"R": att.rotation_at(self.accel_points.subset(c)), "nvec": nvec, "dn": dn, "Bp": Bp, "mu": mu,
                "last": lay["last"][c], "WS": -self.g * self.W_sample @ P["S_a"]}

    def _sample_rate_rows(self, geo: dict, att: Attitude, D, dz_gyro: np.ndarray,
                          a: int, n_c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For motion samples ``a`` to ``a + n_c`` (``geo``: theirs): d r / d z (n_c, 3, 2) of
        their rows, d r / d (the rate derivatives ``D``' parameters) (n_c, 3, P) through the attitude
        at the sample and, on the last knot interval, through the end-point too, and those samples
        (``end``)."""
        c = slice(a, a + n_c)
        Rt = np.swapaxes(geo["R"], 1, 2)  # (stacked matmul: far faster than einsum here)
        Phi = att.sensitivity(D, self.accel_points.subset(c))  # (c, 3, P)
        WS = geo["WS"]
        dr_dz = WS @ (Rt @ geo["dn"] @ geo["Bp"])  # d r / d z (c, 3, 2)
        dr_gyro = (WS @ (Rt @ skew(geo["nvec"]))) @ Phi  # (c, 3, P)
        del Phi
        end = np.flatnonzero(geo["last"])
        mc = geo["mu"]
        dr_gyro[end] += mc[end, None, None] * np.einsum("kia,kap->kip", dr_dz[end], dz_gyro[self.accel.motion[c][end]])
        return dr_dz, dr_gyro, end

    def _sample_rows(self, P, x_l, zK, dz_gyro, dz_dq, att, D, u, block, local, sig, cols_g, jac=True):
        acc = self.accel
        k = len(acc.t)
        j = acc.motion
        p, q = self.p[j], self.qr[j]
        Pg, gl, g = self.glob.size, self.glob.slices, self.g
        lay = self._sample_layout()
        mu = lay["mu"]
        lam = self.lam_acc[:, None]
        waa, wab = self.walk_states(x_l, "wa")
        walk = (1 - lam) * wab[p] + lam * waa[q]
        ub = np.empty((k, 3))  # gravity in the body at each sample, formed chunk by chunk below
        r = np.empty((k, 3))  # the rows' residuals: placed now, filled once every sample's gravity is known
        Jg = block.reserve(3 * k).reshape(k, 3, Pg) if jac and block.globals else None  # written chunk by chunk
        s0 = block(r.reshape(-1), None)
        if Jg is not None:  # M_g and b_g are adjacent columns, k_g apart (cols_g: their 15, -1 where absent)
            assert np.array_equal(cols_g[:12], np.arange(gl["M_g"].start, gl["b_g"].stop))
        WL = np.einsum("ij,ljm->ilm", self.W_sample, _LOWER)  # (3, 6, 3)
        columns = {}  # the entries' local columns: formed only if J_l's sparsity is (once per model)
        for a in range(0, k, SAMPLE_CHUNK):  # the geometry and derivatives of SAMPLE_CHUNK samples at a time
            c = slice(a, a + SAMPLE_CHUNK)
            geo = self._sample_geometry(P, x_l, zK, att, c)
            ub[c] = (np.swapaxes(geo["R"], 1, 2) @ geo["nvec"][:, :, None])[:, :, 0]
            if not jac:
                continue
            n_c = len(acc.t[c])
            dr_dz, dr_gyro, end = self._sample_rate_rows(geo, att, D, dz_gyro, a, n_c)
            jc, mc = j[c], mu[c]
            if Jg is not None:
                Jc = Jg[c]
                Jc[:, :, gl["S_a"]] = -((g * ub[c]) @ WL.reshape(-1, 3).T).reshape(n_c, 3, -1)
                Jc[:, :, gl["b_a"]] = -self.W_sample
                if self.fit_k:
                    Jc[:, :, gl["k_a"]] = -self.W_sample * self.dT_acc[c, None, None]
                Jc[:, :, gl["M_g"].start:gl["b_g"].stop] = dr_gyro[:, :, :12]
                if self.fit_k:
                    Jc[:, :, gl["k_g"]] = dr_gyro[:, :, 12:15]
            vals = np.zeros((n_c, 3, 16))
            vals[:, :, 0:2] = (1 - mc)[:, None, None] * dr_dz
            hi = mc[:, None, None] * dr_dz
            hi[end] = np.einsum("kia,kab->kib", hi[end], dz_dq[jc[end]])
            vals[:, :, 2:4] = hi
            vals[:, :, 4:10] = dr_gyro[:, :, -6:]
            if "wa" in self.walks:
                vals[:, :, 10:13] = -(1 - lam[c])[:, :, None] * self.W_sample
                vals[:, :, 13:16] = -lam[c][:, :, None] * self.W_sample
            keep = lay["keep"][c]

            def where(a=a, n_c=n_c, keep=keep) -> tuple[np.ndarray, np.ndarray]:
                rows = np.broadcast_to((s0 + 3 * np.arange(a, a + n_c)[:, None] + np.arange(3))[:, :, None],
                                       (n_c, 3, 16))
                if "cols" not in columns:
                    columns["cols"] = self._sample_columns(lay)
                return rows[keep], np.broadcast_to(columns["cols"][a:a + n_c, None, :], (n_c, 3, 16))[keep]

            local.flat(where, vals[keep], (s0 + 3 * a, s0 + 3 * (a + n_c) - 1))
        pred = self.accel_prediction(P, g * ub, acc.t, walk)
        np.matmul(acc.y - pred, self.W_sample.T, out=r)
        sig.update(pred_accel_motion=pred, gravity_motion=ub)


class GyroColumns:
    """``JointModel.gyro_columns``' rows, formed when indexed by a slice of rows: the turns' rows
    (a few per motion) at once, the motion samples' ``SAMPLE_CHUNK`` samples at a time, the last
    block kept for the next slice (a structure cell reads a library's rows once, in order). Held
    meanwhile: the attitude and the end-points' derivatives, ``GYRO_CHUNK`` columns at a time
    (memory: the attitude's sensitivities are as wide as the columns), not the rows' array
    (9 columns: 33 MiB per hour of recording)."""

    def __init__(self, model: JointModel, x_g: np.ndarray, x_l: np.ndarray, dy: np.ndarray | RateDerivatives,
                 negate: bool = False):
        self.model, self.x_l, self.negate = model, x_l, negate
        self.P = P = model.unpack(x_g)
        self.n_turn = int(2 * model.K.sum())
        self.shape = (self.n_turn + 3 * len(model.accel.t), dy.shape[2])
        self.turns = np.zeros((self.n_turn, self.shape[1]))
        self.chunks: list[tuple] = []  # per GYRO_CHUNK columns: (columns, z_K, dz_gyro, rate derivatives)
        self._block: tuple[int, np.ndarray | None] = (-1, None)
        if not model.m:
            return
        W_end = np.stack([W[-1] for W in model.Qk_w])
        ends = (np.cumsum(2 * model.K) - 2)[:, None] + np.arange(2)  # (m, 2) each motion's last interval
        self.att = Attitude.integrate(model.quad, model._rates(P, x_l, derivatives=False)[0])
        for a in range(0, dy.shape[2], GYRO_CHUNK):
            cols = slice(a, min(a + GYRO_CHUNK, dy.shape[2]))
            if isinstance(dy, RateDerivatives):
                rate = RateDerivatives(dy.coef, np.einsum("ab,ubk->uak", P["M_g"], dy.basis[:, :, cols]))
            else:
                rate = np.einsum("ab,nbk->nak", P["M_g"], dy[:, :, cols])
            zK, dz_gyro, _, _, D, *_ = model._endpoints(P, x_l, rate_columns=rate, att=self.att)
            self.turns[ends, cols] = W_end @ dz_gyro
            self.chunks.append((cols, zK, dz_gyro, D))
        if negate:
            np.negative(self.turns, out=self.turns)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, rows: slice) -> np.ndarray:
        a, b, _ = rows.indices(len(self))
        out = np.zeros((max(b - a, 0), self.shape[1]))
        if a < min(b, self.n_turn):
            out[:min(b, self.n_turn) - a] = self.turns[a:b]
        r = max(a, self.n_turn)
        while r < b:  # the samples' rows, three a sample, by blocks of samples
            first, block = self._samples((r - self.n_turn) // 3 // SAMPLE_CHUNK)
            lo = self.n_turn + 3 * first
            hi = min(lo + len(block), b)
            out[r - a:hi - a] = block[r - lo:hi - lo]
            r = hi
        return out

    def _samples(self, i: int) -> tuple[int, np.ndarray]:
        """Block ``i`` of the motion samples: its first sample and its rows (3 n, k)."""
        if self._block[0] != i:
            self._block = (-1, None)  # the last block goes before the next is formed
            model, first = self.model, i * SAMPLE_CHUNK
            n_c = min(SAMPLE_CHUNK, len(model.accel.t) - first)
            block = np.zeros((n_c, 3, self.shape[1]))
            for cols, zK, dz_gyro, D in self.chunks:
                geo = model._sample_geometry(self.P, self.x_l, zK, self.att, slice(first, first + n_c))
                block[:, :, cols] = model._sample_rate_rows(geo, self.att, D, dz_gyro, first, n_c)[1]
            if self.negate:
                np.negative(block, out=block)
            self._block = (i, block.reshape(3 * n_c, -1))
        return i * SAMPLE_CHUNK, self._block[1]

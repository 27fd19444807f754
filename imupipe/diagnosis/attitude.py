"""The attitude inside every motion, integrated from the calibrated gyro, and its sensitivities.

Gyro samples are point values of a smooth body rate. Between consecutive samples
``t_s`` and ``t_s+1`` (step ``d``) the rotation vector is the end-corrected
trapezoid (Gregory's rule, fourth order for a smooth rate about a fixed axis)::

    a_s = d (w_s + w_s+1) / 2 - d^2 / 12 (w'_s+1 - w'_s),     w' by central differences

and the rotation from a motion's first sample to any instant is the ordered
product of the steps' exact rotations ``exp(a_s)`` up to it, the last one partial
(``w_s tau + (w_s+1 - w_s) tau^2 / (2 d)``). The turn rotation of the endpoint model
is the product over the whole motion, so rests, turns and every sample in between
share one attitude. All motions are flattened into one ragged array: products by
a segmented log-depth scan (no padding, no loop per sample); the steps are a
sparse linear stencil of the rates, applied alike to their derivatives.

Sensitivities: changing step ``s``'s rotation vector by ``delta a`` turns the
attitude at any later instant by ``phi = P_s J_l(a_s) delta a`` in the motion's
start frame (``P_s`` the rotation before step ``s``, ``J_l`` the left Jacobian of
``exp``), exactly to first order; ``sensitivity`` sums this over the steps.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..rotations import quat_exp, quat_mul_into, quat_to_matrix, skew

_SMALL = 1e-4
# steps (or instants) whose attitude quantities are formed at once: temporaries of a few MiB, which the
# allocator reuses, where whole-recording ones are fresh pages the kernel clears every time
STEP_CHUNK = 1 << 12
_PATTERN_PROBE = 256  # rows of local nodes that tell whether their patterns repeat


def left_jacobian(a: np.ndarray) -> np.ndarray:
    """(..., 3, 3) left Jacobian of SO(3)'s exp at rotation vectors ``a`` (..., 3)."""
    th2 = np.einsum("...i,...i->...", a, a)
    th = np.sqrt(th2)
    small = th < _SMALL
    safe = np.where(small, 1.0, th)
    c1 = np.where(small, 0.5 - th2 / 24.0, (1 - np.cos(safe)) / safe**2)
    c2 = np.where(small, 1.0 / 6.0 - th2 / 120.0, (safe - np.sin(safe)) / safe**3)
    K = skew(a)
    return np.eye(3) + c1[..., None, None] * K + c2[..., None, None] * (K @ K)


def _run_bounds(seg: np.ndarray) -> np.ndarray:
    """(runs + 1,) where each run of equal ``seg`` (n,) values starts, then n (n > 0)."""
    return np.flatnonzero(np.r_[True, seg[1:] != seg[:-1], True])


def _whole_runs(seg: np.ndarray, size: int) -> list[tuple[int, int]]:
    """Consecutive ranges of whole runs of equal ``seg``, each about ``size`` long or one run."""
    ranges, a = [], 0
    bounds = _run_bounds(seg) if len(seg) else []
    for b in bounds[1:]:
        if b - a >= size or b == bounds[-1]:
            ranges.append((a, int(b)))
            a = int(b)
    return ranges


def segmented_scan(q: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Inclusive ordered products of quaternions ``q`` (n, 4) within runs of equal ``seg`` (n,)
    (Hillis-Steele: log2 of the longest run's length vectorised passes, not of n; each pass
    multiplies every pair of slices and keeps the products within a run: 3x faster than
    gathering and scattering those pairs), on the quaternions' components in rows."""
    n = len(q)
    longest = int(np.diff(_run_bounds(seg)).max()) if n else 0
    Q, prod, scratch = np.ascontiguousarray(q.T), np.empty((4, n)), np.empty(n)
    off = 1
    while off < longest:
        k = n - off
        quat_mul_into(Q[:, :-off], Q[:, off:], prod[:, :k], scratch[:k])
        np.copyto(Q[:, off:], prod[:, :k], where=seg[off:] == seg[:-off])
        off *= 2
    q = np.ascontiguousarray(Q.T)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def segmented_cumsum(x: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Inclusive cumulative sums of ``x`` (n, ...) along axis 0 restarting at each new ``seg``
    (one cumulative sum per run: no running sum carried across runs, which would cost a
    gather and a subtraction of the whole array and lose digits)."""
    out = np.empty_like(x)
    if not len(x):
        return out
    bounds = _run_bounds(seg)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        np.cumsum(x[a:b], axis=0, out=out[a:b])
    return out


def _integrals(t: np.ndarray, motion: np.ndarray, s: np.ndarray, tau: np.ndarray,
               width: int = 6) -> sp.csr_matrix:
    """(k, N) weights of the integral of the rate from sample ``s`` (k,) to ``tau`` (k,) s after it:
    the integral of the polynomial through ``width`` samples of the motion around the step
    (centred where the motion allows), exact for rates of degree ``width - 1``; ``STEP_CHUNK``
    rows at a time (their temporaries are ``width``^2 per row)."""
    if len(s) <= STEP_CHUNK:
        return _integral_rows(t, motion, s, tau, width)
    return sp.vstack([_integral_rows(t, motion, s[a:a + STEP_CHUNK], tau[a:a + STEP_CHUNK], width)
                      for a in range(0, len(s), STEP_CHUNK)], format="csr")


def _integral_rows(t: np.ndarray, motion: np.ndarray, s: np.ndarray, tau: np.ndarray,
                   width: int) -> sp.csr_matrix:
    k, N = len(s), len(t)
    if not k:
        return sp.csr_matrix((0, N))
    first = np.searchsorted(motion, motion[s], "left")
    count = np.searchsorted(motion, motion[s], "right") - first
    w = np.minimum(count, width)
    lo = np.clip(s - (w - 1) // 2, first, first + count - w)  # window start, inside the motion
    j = np.arange(width)
    valid = j[None, :] < w[:, None]
    idx = np.where(valid, lo[:, None] + j, s[:, None])
    d = np.where(s + 1 < first + count, t[np.minimum(s + 1, N - 1)] - t[s], 1.0)
    d = np.where(d > 0, d, 1.0)
    x = (t[idx] - t[s][:, None]) / d[:, None]  # (k, width) local nodes
    coef = _node_coefficients(x, valid)
    u = (tau / d)[:, None]
    mono = np.where(valid, u ** (j + 1) / (j + 1), 0.0)  # integral of x^j from 0 to u
    wts = d[:, None] * np.einsum("km,kmn->kn", mono, coef)
    wts = np.where(valid, wts, 0.0)
    return sp.csr_matrix((wts.ravel(), (np.repeat(np.arange(k), width), idx.ravel())), shape=(k, N))


def _node_coefficients(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(k, monomial, node) the polynomial coefficients per node's value: the inverse of each
    row's Vandermonde matrix of nodes ``x`` (k, w) (padded nodes and monomials form an identity
    block). Samples at a steady rate give a few dozen distinct rows of nodes: each is inverted
    once (the same numbers; checked on the first ``_PATTERN_PROBE`` rows, as jittered time
    stamps make every row distinct)."""
    key = np.ascontiguousarray(np.where(valid, x, np.inf))  # a padded node: a pattern of its own
    rows = key.view(np.dtype((np.void, key.itemsize * key.shape[1])))[:, 0]
    if len(rows) > _PATTERN_PROBE and 2 * len(np.unique(rows[:_PATTERN_PROBE])) <= _PATTERN_PROBE:
        _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
        return _node_coefficients(x[first], valid[first])[inverse]
    j = np.arange(x.shape[1])
    # rows: nodes, columns: monomials
    V = np.where(valid[:, :, None] & valid[:, None, :], x[:, :, None] ** j[None, None, :], 0.0)
    V += np.where(~valid[:, :, None] & (j[:, None] == j[None, :])[None], 1.0, 0.0)
    return np.linalg.inv(V)


@dataclass(frozen=True)
class RateDerivatives:
    """(N, 3, P) derivatives of N calibrated rates w.r.t. P parameters, held as ``coef`` (N, B)
    times ``basis`` (B, 3, P) with B small (a rate is linear in a few per-sample quantities):
    weighted sums over samples then cost B columns, not 3 P."""

    coef: np.ndarray
    basis: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.coef), *self.basis.shape[1:])

    def __len__(self) -> int:
        return len(self.coef)

    def dense(self) -> np.ndarray:
        return (self.coef @ self.basis.reshape(len(self.basis), -1)).reshape(self.shape)


def weighted(W: sp.spmatrix, D: np.ndarray | RateDerivatives) -> np.ndarray:
    """(k, 3, P) ``sum_n W[:, n] D[n]`` for rate derivatives ``D`` (N, 3, P), dense or factored."""
    if isinstance(D, RateDerivatives):
        return ((W @ D.coef) @ D.basis.reshape(len(D.basis), -1)).reshape(W.shape[0], 3, -1)
    return (W @ D.reshape(len(D), -1)).reshape(W.shape[0], 3, -1)


def by_motion(motion: np.ndarray, count: int) -> list[slice]:
    """Each motion's slice of a ``motion`` index array sorted by motion (empty where it has no
    sample): a loop over the motions then costs their own samples, not every sample each time."""
    edges = np.searchsorted(motion, np.arange(count + 1))
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _joined(parts: list[np.ndarray]) -> np.ndarray:
    """``np.concatenate(parts)``; the array they are views of, without a copy, when they lie one
    after the other and cover it whole (``Turns.from_tables``' turns: a model of them holds their
    samples once)."""
    base = parts[0].base
    if (base is not None and base.flags.c_contiguous and base.dtype == np.float64
            and base.shape[1:] == parts[0].shape[1:]
            and all(x.base is base and x.flags.c_contiguous for x in parts)
            and sum(len(x) for x in parts) == len(base)):
        at = base.__array_interface__["data"][0]
        for x in parts:
            if len(x) and x.__array_interface__["data"][0] != at:  # (an empty view's may be anywhere)
                break
            at += x.nbytes
        else:
            return base
    return np.concatenate(parts)


@dataclass(frozen=True)
class MotionSamples:
    """The gyro samples of m motions, flattened: ``t`` (N,) s, ``y`` (N, 3) raw gyro, ``motion``
    (N,) motion index (sorted, times increasing within each). ``origin``/``end`` (m,) s: each
    motion's first and last sample time (NaN when empty)."""

    t: np.ndarray
    y: np.ndarray
    motion: np.ndarray
    origin: np.ndarray
    end: np.ndarray

    @classmethod
    def from_turns(cls, t: Sequence[np.ndarray], y: Sequence[np.ndarray]) -> MotionSamples:
        m = len(t)
        origin = np.array([x[0] if len(x) else np.nan for x in t], float)
        end = np.array([x[-1] if len(x) else np.nan for x in t], float)
        if not m or not sum(len(x) for x in t):
            return cls(np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64), origin, end)
        return cls(_joined([np.asarray(x, float) for x in t]),
                   _joined([np.asarray(x, float).reshape(-1, 3) for x in y]),
                   np.repeat(np.arange(m), [len(x) for x in t]).astype(np.int64), origin, end)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def count(self) -> int:
        return len(self.origin)


@dataclass(frozen=True)
class Points:
    """Instants inside motions: ``h`` (k,) the step holding each (-1: the motion has no step),
    ``tau`` (k,) s into it, ``W`` (k, N) the weights of the rate integral up to the instant
    within its step."""

    h: np.ndarray
    tau: np.ndarray
    W: sp.csr_matrix

    def subset(self, idx: np.ndarray | slice) -> Points:
        return Points(self.h[idx], self.tau[idx], self.W[idx])


class Quadrature:
    """What integrating the motions needs from the time stamps alone (computed once): the steps
    (``step`` (S,) the first sample of each), their weights ``A`` (S, N) and ``ranges`` of whole
    motions' steps, each about ``STEP_CHUNK`` long, to form the attitude by."""

    def __init__(self, samples: MotionSamples):
        self.samples = samples
        same_next = np.r_[samples.motion[1:] == samples.motion[:-1], False] if len(samples) else \
            np.zeros(0, bool)
        self.step = np.flatnonzero(same_next)  # a step starts at every sample with a successor
        self.seg = samples.motion[self.step]
        self.A = _integrals(samples.t, samples.motion, self.step,
                            samples.t[self.step + 1] - samples.t[self.step])
        self.last = np.flatnonzero(np.r_[self.seg[1:] != self.seg[:-1], True]) if len(self.step) else \
            np.zeros(0, int)
        self.ranges = _whole_runs(self.seg, STEP_CHUNK)
        self.last_integrated: tuple | None = None  # ``Attitude.integrate``'s last rates and result

    def points(self, t: np.ndarray, motion: np.ndarray) -> Points:
        """The instants ``t`` (k,) s of motions ``motion`` (k,) (clipped to each motion's span)."""
        ms = self.samples
        t = np.asarray(t, float)
        k = len(t)
        lo = np.searchsorted(ms.motion, motion, "left")  # each motion's first sample
        hi = np.searchsorted(ms.motion, motion, "right") - 1
        has = hi > lo
        if not has.any():
            return Points(np.full(k, -1), np.zeros(k), sp.csr_matrix((k, len(ms))))
        base, span = ms.t.min(), 2 * (np.ptp(ms.t) + 1.0)
        tc = np.clip(t, ms.t[np.minimum(lo, len(ms) - 1)], ms.t[np.maximum(hi, 0)])
        key = ms.motion * span + (ms.t - base)
        s = np.clip(np.searchsorted(key, motion * span + (tc - base), "right") - 1, lo, np.maximum(hi - 1, lo))
        step_of = np.full(len(ms), -1)
        step_of[self.step] = np.arange(len(self.step))
        h = np.where(has, step_of[s], -1)
        tau = np.where(has, np.clip(tc - ms.t[s], 0, None), 0.0)
        W = _integrals(ms.t, ms.motion, np.where(has, s, 0), tau)
        return Points(h, tau, (sp.diags(has.astype(float)) @ W).tocsr())


@dataclass(frozen=True)
class Attitude:
    """Integrated rotations of every motion under calibrated rates ``omega`` (N, 3) rad/s.

    ``q_before`` (S, 4) the rotation (body at the step's start -> body at the motion's start)
    before each step as a quaternion (its matrices, ``rotations_before``, are formed where used:
    9 numbers a step held through a fit instead of 4), ``total`` (m, 3, 3) each motion's rotation
    at its last sample (identity for motions of fewer than two samples). The steps' rotation
    vectors are formed where used too (``quad.A[s] @ omega``, the same bits by rows as at once).
    """

    quad: Quadrature
    omega: np.ndarray
    q_before: np.ndarray
    total: np.ndarray

    @classmethod
    def integrate(cls, quad: Quadrature, omega: np.ndarray) -> Attitude:
        """The attitude under ``omega``; the one integrated last when ``omega`` equals its rates:
        a fit asks again for the point it has just evaluated (a trial taken, then its Jacobian;
        its solution, then the map's signals), 16 of 29 integrations of a standard run."""
        last = quad.last_integrated
        if last is not None and np.array_equal(last[0], omega):
            return cls(quad, *last)
        quad.last_integrated = last = None  # let its arrays go before the new ones are formed
        a = quad.A @ omega if len(quad.step) else np.zeros((0, 3))  # the steps' rotation vectors
        seg = quad.seg
        q_before = np.empty((len(a), 4))
        total = np.tile(np.eye(3), (quad.samples.count, 1, 1))
        for lo, hi in quad.ranges:  # whole motions: a product never crosses a range's edge
            q = segmented_scan(quat_exp(a[lo:hi]), seg[lo:hi])  # after each step
            prev = q_before[lo:hi]
            prev[0] = [1.0, 0.0, 0.0, 0.0]
            prev[1:] = q[:-1]
            prev[np.r_[True, seg[lo + 1:hi] != seg[lo:hi - 1]]] = [1.0, 0.0, 0.0, 0.0]
            ends = slice(*np.searchsorted(quad.last, [lo, hi]))
            total[seg[quad.last[ends]]] = quat_to_matrix(q[quad.last[ends] - lo])
        quad.last_integrated = (omega, q_before, total)  # arrays, not the attitude: no cycle through quad
        return cls(quad, omega, q_before, total)

    def rotations_before(self, steps: np.ndarray | slice) -> np.ndarray:
        """(k, 3, 3) the rotation before each of ``steps`` (indices or a slice of steps)."""
        return quat_to_matrix(self.q_before[steps])

    def rotation_at(self, pts: Points) -> np.ndarray:
        """(k, 3, 3) rotation (body at the instant -> body at the motion's start)."""
        if not len(pts.h):
            return np.zeros((0, 3, 3))
        out = np.empty((len(pts.h), 3, 3))
        for lo in range(0, len(pts.h), STEP_CHUNK):
            c = slice(lo, lo + STEP_CHUNK)
            h = pts.h[c]
            R0 = self.rotations_before(np.maximum(h, 0)) if len(self.q_before) else np.tile(np.eye(3), (len(h), 1, 1))
            R0 = np.where((h >= 0)[:, None, None], R0, np.eye(3))
            np.matmul(R0, quat_to_matrix(quat_exp(pts.W[c] @ self.omega)), out=out[c])
        return out

    def _end_totals(self, D: np.ndarray) -> np.ndarray:
        """The sums through each motion's last step (m', 3, P) of each step's start-frame
        attitude change per unit parameter change; by ranges of steps, each motion's sum in the
        order of a running sum (the same bits), so temporaries stay small."""
        quad = self.quad
        last = np.empty((len(quad.last), 3, D.shape[2]))
        for lo, hi in quad.ranges:
            ends = slice(*np.searchsorted(quad.last, [lo, hi]))
            per = self._per_step(D, lo, hi, running=False)[0]
            bounds = _run_bounds(quad.seg[lo:hi])
            last[ends] = [per[a:b].sum(axis=0) for a, b in itertools.pairwise(bounds)]
        return last

    def _per_step(self, D: np.ndarray, lo: int, hi: int, running: bool = True
                  ) -> tuple[np.ndarray, np.ndarray | None]:
        """Steps ``lo`` to ``hi`` (whole motions): each one's start-frame attitude change per unit
        parameter change (hi - lo, 3, P) and their running sums within each motion (``running``;
        else None)."""
        s = slice(lo, hi)
        A = self.quad.A[s]
        per = (self.rotations_before(s) @ left_jacobian(A @ self.omega)) @ weighted(A, D)
        return per, segmented_cumsum(per, self.quad.seg[s]) if running else None

    def sensitivity(self, D: np.ndarray, pts: Points) -> np.ndarray:
        """(k, 3, P) start-frame attitude change per unit change of parameters at the instants
        ``pts``, given ``D`` (N, 3, P) each sample's calibrated-rate derivative. The sums before
        each step are formed here over the whole motions holding the instants' steps alone (a
        few instants at a time: no (S, 3, P) array, which a long recording's fit would hold)."""
        P = D.shape[2]
        k = len(pts.h)
        if not k or not len(self.q_before):
            return np.zeros((k, 3, P))
        hh = np.maximum(pts.h, 0)
        if (pts.h >= 0).any():
            seg = self.quad.seg
            first = int(np.searchsorted(seg, seg[pts.h[pts.h >= 0].min()], "left"))  # its motion's first step
            per, run = self._per_step(D, first, int(hh.max()) + 1)
            out = (run - per)[np.maximum(hh - first, 0)]
        else:
            out = np.zeros((k, 3, P))
        part = self.rotations_before(hh) @ left_jacobian(pts.W @ self.omega)
        part = part @ weighted(pts.W, D)
        out += part
        out[pts.h < 0] = 0.0
        return out

    def end_sensitivity(self, D: np.ndarray) -> np.ndarray:
        """(m, 3, P) the same at each motion's last sample (zeros for motions without steps)."""
        out = np.zeros((self.quad.samples.count, 3, D.shape[2]))
        if len(self.q_before):
            out[self.quad.seg[self.quad.last]] = self._end_totals(D)
        return out

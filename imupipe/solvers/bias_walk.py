"""Gyro bias random walk as a nuisance: its intensity from the rests, the bias at each turn.

The gyro bias is ``b(t) = b0 + k (T - 25) + w(t)`` with ``w`` a random walk of
intensity ``q`` (rad^2/s^3 per axis: the variance grows by ``q`` per second)
centred on the session (``w`` averages to zero over it, so ``b0`` stays the
session's mean level). Each rest mean and each turn sees ``w`` averaged over its
own interval; for a Wiener process these averages are jointly Gaussian with
covariance ``q K``, ``K`` the centred Brownian kernel of interval averages
(``centred_kernel``). Given the rests'
gyro residuals ``r = y - b0 - k dT`` (white covariance ``Sigma_i / n_i``), the
bias at turn ``j`` is the Gaussian conditional mean (a fixed-interval smoother
written as GLS)::

    w_j = C_jr V^-1 r      V = blockdiag(Sigma_i / n_i) + K_rr (x) diag(q)
    P_j = C_jj - C_jr V^-1 C_rj                         (its uncertainty, rad^2/s^2)

With ``q = 0`` every term vanishes and the constant-bias model is recovered
exactly. ``q`` is the restricted maximum likelihood (REML) estimate from the rest
means, with the level (and ``dT`` when ``k`` is fitted) profiled out, beside a
rest-to-rest scatter without time correlation (an attitude effect, left unmodelled
so that the residuals still show it).
Dense matrices: sessions of a few hundred rests. Derivation: docs/method-b.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.optimize import minimize_scalar

from ..observations import Rests, Turns

_GRID = np.linspace(-4.0, 10.0, 15)  # log10 of q L / (median white variance of a mean)
_NU_GRID = np.linspace(-1.0, 5.0, 7)  # log10 of the extra rest scatter / the same
MIN_LR = 2.71  # -2 log likelihood ratio for q > 0: 5 % false alarms (boundary, 1 parameter)


def rest_intervals(rests: Rests) -> tuple[np.ndarray, np.ndarray]:
    """(n,) midpoints and (n,) lengths, s, of the rests."""
    return 0.5 * (rests.t_start_s + rests.t_end_s), rests.t_end_s - rests.t_start_s


def turn_intervals(rests: Rests, turns: Turns) -> tuple[np.ndarray, np.ndarray]:
    """(m,) midpoints and (m,) lengths, s, of the turns (the gap between their rests if empty)."""
    a = np.array([t[0] if len(t) else np.nan for t in turns.t])
    b = np.array([t[-1] if len(t) else np.nan for t in turns.t])
    a = np.where(np.isfinite(a), a, rests.t_end_s[turns.before])
    b = np.where(np.isfinite(b), b, rests.t_start_s[turns.after])
    return 0.5 * (a + b), np.maximum(b - a, 0.0)


def centred_kernel(s: np.ndarray, ds: np.ndarray, t: np.ndarray, dt: np.ndarray, t0: float,
                   span: float, same: bool = False) -> np.ndarray:
    """(len(s), len(t)) covariance of the averages of a unit Wiener process minus its mean
    over ``[t0, t0 + span]``, over disjoint intervals of midpoints ``s``/``t`` and lengths
    ``ds``/``dt`` (s); ``same``: ``s`` and ``t`` are the same intervals (the diagonal is
    each interval's own variance). Exact for intervals inside the span."""
    s, t = s - t0, t - t0
    K = np.minimum.outer(s, t)
    if same:
        K[np.diag_indices_from(K)] -= ds / 6

    def g(m: np.ndarray, d: np.ndarray) -> np.ndarray:  # cov(average over the interval, mean)
        return m - (m**2 + d**2 / 12) / (2 * span)

    return K - g(s, ds)[:, None] - g(t, dt)[None, :] + span / 3


def _reml(q: float, K: np.ndarray, var: np.ndarray, r: np.ndarray, X: np.ndarray) -> float:
    """-2 log restricted likelihood (up to a constant) of ``r`` (n,) with covariance
    ``diag(var) + q K`` and the regressors ``X`` (n, p) profiled out."""
    try:
        L = np.linalg.cholesky(np.diag(var) + q * K)
    except np.linalg.LinAlgError:
        return np.inf
    Lr = solve_triangular(L, r, lower=True)
    LX = solve_triangular(L, X, lower=True)
    A = LX.T @ LX
    e = Lr - LX @ np.linalg.solve(A, LX.T @ Lr)
    return float(2 * np.log(np.diag(L)).sum() + np.linalg.slogdet(A)[1] + e @ e)


def estimate_intensity(rests: Rests, resid: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, float]:
    """REML random-walk intensity ``q`` (3,), rad^2/s^3, one value for the three axes (pooled:
    a per-axis estimate from one session scatters by a factor 2), and the rest-to-rest
    scatter ``nu`` (rad/s)^2 that is *not* temporally correlated (e.g. a g-sensitivity seen
    at each attitude: the fit does not model it), from the rests' gyro residuals ``resid``
    (n, 3) rad/s with the regressors ``X`` (n, p) (a constant column, and ``dT`` when ``k``
    is fitted) profiled out. ``q = 0`` unless the walk improves the restricted likelihood
    significantly (``MIN_LR``)."""
    mid, length = rest_intervals(rests)
    t0, span = float(rests.t_start_s.min()), float(np.ptp(np.r_[rests.t_start_s, rests.t_end_s]))
    if len(rests) < 4 or span <= 0:
        return np.zeros(3), 0.0
    K = centred_kernel(mid, length, mid, length, t0, span, same=True)
    var = np.diagonal(rests.cov_of_mean("gyro"), axis1=1, axis2=2)
    U, sv, _ = np.linalg.svd(X, full_matrices=False)
    X = U[:, sv > 1e-8 * sv[0]]  # the same column space, without collinear regressors

    def cost(q: float, nu: float) -> float:
        return sum(_reml(q, K, var[:, a] + nu, resid[:, a], X) for a in range(3))

    v0 = float(np.median(var))
    qs = np.r_[0.0, v0 / span * 10.0**_GRID]
    nus = np.r_[0.0, v0 * 10.0**_NU_GRID]
    C = np.array([[cost(q, nu) for nu in nus] for q in qs])
    i, j = np.unravel_index(np.argmin(C), C.shape)
    nu = float(nus[j])
    if i == 0 or C[0].min() - C[i, j] < MIN_LR:
        return np.zeros(3), float(nus[np.argmin(C[0])])
    x = np.log10(qs[i] * span / v0)
    res = minimize_scalar(lambda x: cost(v0 / span * 10.0**x, nu), bounds=(x - 0.5, x + 0.5),
                          method="bounded", options={"xatol": 0.01})
    q = v0 / span * 10.0 ** float(res.x) if res.fun < C[i, j] else float(qs[i])
    return np.full(3, q), nu


@dataclass(frozen=True)
class BiasWalk:
    """The random-walk part of the gyro bias over n rests and m turns.

    ``q`` (3,) rad^2/s^3; ``whitener`` (3n, 3n) ``L^-1`` of the rests' gyro-mean
    covariance ``V`` (rest-major: index ``3 i + axis``); ``gain`` (3m, 3n) maps the
    rests' residuals to the turns' mean bias offsets; ``cov`` (m, 3, 3) (rad/s)^2 the
    uncertainty of those offsets. ``q = 0``: inactive (empty whitener, zero gain and cov).
    """

    q: np.ndarray
    whitener: np.ndarray
    gain: np.ndarray
    cov: np.ndarray

    @property
    def active(self) -> bool:
        return bool(np.any(self.q > 0))

    @classmethod
    def build(cls, rests: Rests, turns: Turns, q: np.ndarray) -> BiasWalk:
        n, m = len(rests), len(turns)
        q = np.clip(np.asarray(q, float), 0, None)
        blocks = rests.cov_of_mean("gyro")
        if not np.any(q > 0):  # the white model: the caller whitens rest by rest
            return cls(q, np.zeros((0, 0)), np.zeros((3 * m, 3 * n)), np.zeros((m, 3, 3)))
        r_mid, r_len = rest_intervals(rests)
        t_mid, t_len = turn_intervals(rests, turns)
        t0, span = float(rests.t_start_s.min()), float(np.ptp(np.r_[rests.t_start_s, rests.t_end_s]))
        Q = np.diag(q)
        V = np.kron(centred_kernel(r_mid, r_len, r_mid, r_len, t0, span, same=True), Q)
        for i in range(n):
            V[3 * i: 3 * i + 3, 3 * i: 3 * i + 3] += blocks[i]
        L = np.linalg.cholesky(V)
        W = solve_triangular(L, np.eye(3 * n), lower=True)
        C_tr = np.kron(centred_kernel(t_mid, t_len, r_mid, r_len, t0, span), Q)  # (3m, 3n)
        gain = cho_solve(cho_factor(V, lower=True), C_tr.T).T
        k_tt = centred_kernel(t_mid, t_len, t_mid, t_len, t0, span, same=True).diagonal()
        G3, C3 = gain.reshape(m, 3, 3 * n), C_tr.reshape(m, 3, 3 * n)
        P = k_tt[:, None, None] * Q - np.einsum("mak,mbk->mab", G3, C3)
        P = 0.5 * (P + np.swapaxes(P, 1, 2))
        w, U = np.linalg.eigh(P)  # clip rounding below zero
        P = np.einsum("mab,mb,mcb->mac", U, np.clip(w, 0, None), U)
        return cls(q, W, gain, P)

    def offsets(self, resid: np.ndarray) -> np.ndarray:
        """(m, 3) rad/s: the turns' mean bias beyond ``b0 + k dT``, from the rests' gyro
        residuals ``resid`` (n, 3) rad/s."""
        return (self.gain @ resid.ravel()).reshape(-1, 3)

    def rotation_cov(self, duration: np.ndarray, M_g: np.ndarray) -> np.ndarray:
        """(m, 3, 3) rad^2: the turns' rotation-vector noise from the offsets' uncertainty
        (a mean bias error ``e`` over ``duration`` (m,) s rotates by ``M_g e duration``)."""
        return duration[:, None, None] ** 2 * (M_g @ self.cov @ M_g.T)

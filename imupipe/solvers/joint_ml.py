"""Joint maximum-likelihood refinement of accelerometer and gyroscope (beyond both papers).

One estimator over every rest and every turn. The unknowns are the
accelerometer's forward matrix ``S_a`` (lower-triangular: the accelerometer
frame is the reference, Eq. (1.3) of Chikrin & Golousov) and bias ``b_a``, the
gyroscope's correction ``M_g`` and bias ``b_g``, and, as nuisance parameters,
the true gravity direction ``u_i`` at every rest. The measurements, each
whitened by its own noise::

    accel mean at rest i    y_a,i = S_a (g u_i) + b_a          cov: rest covariance / count
    gyro mean at rest i     y_g,i = b_g                        cov: rest covariance / count
    turn j from p to q      u_q = R_j(M_g, b_g)^T u_p          cov: integrated gyro noise

plus, when the rests span a range of temperatures, the bias temperature
coefficients ``k_a``, ``k_g`` (``+ k (T - 25)`` in every line above), so the
estimate is maximum likelihood for white sensor noise, and its
covariance is ``(J^T J)^-1`` of the whitened Jacobian at the optimum (the
Cramer-Rao bound when evaluated at the truth). The gyro bias may also walk
(``bias_walk.py``): its intensity is estimated from the rests, the rests' gyro
means are then whitened jointly, each turn takes the walk smoothed from the rests
and carries its uncertainty; with no walk this is the constant-bias model. The
earth's rotation is not in the model (15 deg/h; it biases ``b_g`` by its projection).

It starts from any answer (method A's or B's). A start in another frame (not
lower-triangular) is moved to the lower-triangular gauge, refined, and turned
back, so the result keeps the frame convention of the start; the covariance is
then conditional on that frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy.optimize import least_squares

from ..components import Params
from ..errors import SolverError
from ..models import T_REF_C, TriadCalibration
from ..observations import Rests, TriadFit, Turns
from ..rotations import carry, pad_turns, rotation_angle, turn_rotations
from .bias_walk import BiasWalk, estimate_intensity
from .gyro_integration import drop_saturated, saturated_turns
from .triad_covariance import shape_basis
from .turn_model import (
    carried_cov,
    gyro_sample_cov,
    integrated_gyro_cov,
    tangent_basis,
    turn_temperature,
)

N_MAIN = 21  # S_a (6), b_a (3), M_g (9), b_g (3); then k_a, k_g (6) when fitted
N_OUT = 30  # M_a (9), b_a (3), M_g (9), b_g (3), k_a (3), k_g (3)
MIN_SPREAD_C = 2.0  # temperature range of the rests above which "auto" fits k
_LOWER = shape_basis("lower")  # (6, 3, 3)


class JointMLParams(Params):
    max_nfev: int = 30
    """Gauss-Newton / Levenberg-Marquardt iterations allowed."""
    keep_frame: bool = True
    """Return the result in the frame of the starting calibration (else the lower-triangular one)."""
    saturation_rad_s: float | None = None
    """The gyro's range when known; None: detect clipped turns from the data (left out)."""
    fit_temperature: Literal["auto", "yes", "no"] = "auto"
    """Also fit the bias temperature coefficients k of both triads (auto: when the rests span
    2 degC or more); otherwise the start's k are applied unchanged. A start with ``sigma_k``
    (a thermal stage's warm-up fit) enters the fit as a prior measurement of k."""
    gyro_bias_rw: float | None = Field(None, ge=0)
    """Gyro bias random walk, rad/s/sqrt(s), per axis; None: estimated from the rests (REML);
    0: a constant bias ``b0 + k (T - 25)`` (no drift model)."""


@dataclass(frozen=True)
class JointObservations:
    """What ``refine_joint`` hands to a ``joint`` solver.

    ``rests``/``turns`` as segmented (raw, sensor axes, SI); ``gravity`` the
    local magnitude m/s^2; ``accel``/``gyro`` the starting calibrations (their
    temperature coefficients ``k`` are kept and applied, not refined).
    """

    rests: Rests
    turns: Turns
    gravity: float
    accel: TriadCalibration
    gyro: TriadCalibration


@dataclass(frozen=True)
class JointFit:
    """``triads``: refined ``TriadFit`` per sensor; ``cov`` (30, 30) over
    ``(M_a.ravel(), b_a, M_g.ravel(), b_g, k_a, k_g)`` (k rows zero when not fitted);
    ``details`` fit statistics; ``k`` the temperature coefficients used per sensor
    (fitted or the start's), ``sigma_k`` their 1-sigma when fitted; ``rest_gravity``
    (n, 3) the fitted unit gravity (nuisance) at every rest, instrument frame of the
    result; ``turns_used`` (m,) bool, the turns of the observations the fit used."""

    triads: dict[str, TriadFit]
    cov: np.ndarray
    details: dict[str, Any] = field(default_factory=dict)
    k: dict[str, np.ndarray] = field(default_factory=dict)
    sigma_k: dict[str, np.ndarray] = field(default_factory=dict)
    rest_gravity: np.ndarray | None = None
    turns_used: np.ndarray | None = None


def _whitener(cov: np.ndarray) -> np.ndarray:
    """(n, k, k) ``L^-1`` with ``L L^T = cov`` (n, k, k)."""
    return np.linalg.inv(np.linalg.cholesky(cov))


class JointProblem:
    """The whitened residuals and Jacobian of the joint likelihood.

    ``x = (S_a lower (6), b_a (3), M_g (9), b_g (3), [k_a (3), k_g (3)], delta (n, 2))``;
    the rest directions are ``u_i = normalise(u0_i + B_i delta_i)``. With ``fit_k`` the
    temperature coefficients are unknowns (identifiable when the rests span a range of
    temperatures); otherwise ``k_a``/``k_g`` are applied as given. ``walk``: the gyro bias
    random walk (None or inactive: a constant bias). Built once; the turn weights are
    fixed at the start so the cost is one quadratic form.
    """

    def __init__(self, rests: Rests, turns: Turns, gravity: float, S_a: np.ndarray, b_a: np.ndarray,
                 M_g: np.ndarray, b_g: np.ndarray, k_a: np.ndarray | None = None,
                 k_g: np.ndarray | None = None, u0: np.ndarray | None = None, fit_k: bool = False,
                 sigma_k: np.ndarray | None = None, walk: BiasWalk | None = None):
        self.g = float(gravity)
        n = len(rests)
        self.fit_k = fit_k
        self.nm = N_MAIN + (6 if fit_k else 0)
        self.dT = np.where(np.isfinite(rests.temperature), rests.temperature, T_REF_C) - T_REF_C
        self.k_a = np.zeros(3) if k_a is None else np.asarray(k_a, float)
        self.k_g = np.zeros(3) if k_g is None else np.asarray(k_g, float)
        self.y_a = rests.need("accel")
        self.y_g = rests.need("gyro")
        self.W_a = _whitener(rests.cov_of_mean("accel"))
        self.W_g = _whitener(rests.cov_of_mean("gyro"))
        self.p, self.q = np.asarray(turns.before), np.asarray(turns.after)
        self.rate, self.dt = pad_turns(turns.t, turns.gyro)
        # Bias random walk (bias_walk.py): rests whitened jointly, each turn's bias smoothed.
        self.walk = walk if walk is not None and walk.active else None
        self.dT_turn = turn_temperature(rests, turns) - T_REF_C  # degC - 25
        if u0 is None:
            u0 = (self.y_a - np.outer(self.dT, self.k_a) - b_a) @ np.linalg.inv(S_a).T
        self.u0 = u0 / np.linalg.norm(u0, axis=1, keepdims=True)
        self.B = tangent_basis(self.u0)
        # Turn noise: white gyro noise integrated over the turn (docs/method-b.md, turn_model).
        cov_phi = integrated_gyro_cov(gyro_sample_cov(rests), self.dt, M_g)
        if self.walk is not None:
            cov_phi = cov_phi + self.walk.rotation_cov(self.dt.sum(axis=1), M_g)
        v = carry(self._rotations(M_g, b_g, self.k_g), self.u0[self.p])
        Eq = self.B[self.q]
        cov2 = np.swapaxes(Eq, -1, -2) @ carried_cov(v, cov_phi) @ Eq
        self.W_t = _whitener(cov2 + 1e-30 * np.eye(2))
        self.n = n
        # A thermal stage's k (6,) with 1-sigma enters as a prior measurement where sigma > 0.
        sk = np.full(6, np.inf) if sigma_k is None else np.asarray(sigma_k, float)
        self.prior = np.flatnonzero(np.isfinite(sk) & (sk > 0)) if fit_k else np.zeros(0, int)
        self.prior_w = 1.0 / sk[self.prior]
        self.k0 = np.concatenate([self.k_a, self.k_g])
        k = [self.k_a, self.k_g] if fit_k else []
        self.x0 = np.concatenate([S_a[np.tril_indices(3)], b_a, M_g.ravel(), b_g, *k, np.zeros(2 * n)])

    # ------------------------------------------------------------------ model
    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(S_a, b_a, M_g, b_g, k_a, k_g, v)``; ``v`` (n, 3) the unnormalised directions."""
        S_a = np.zeros((3, 3))
        S_a[np.tril_indices(3)] = x[:6]
        k_a, k_g = (x[21:24], x[24:27]) if self.fit_k else (self.k_a, self.k_g)
        delta = x[self.nm:].reshape(self.n, 2)
        v = self.u0 + np.einsum("nij,nj->ni", self.B, delta)
        return S_a, x[6:9], x[9:18].reshape(3, 3), x[18:21], k_a, k_g, v

    def _rotations(self, M_g: np.ndarray, b_g: np.ndarray, k_g: np.ndarray) -> np.ndarray:
        bias = b_g + np.outer(self.dT_turn, k_g)  # (m, 3)
        if self.walk is not None:  # the random-walk part smoothed from the rests' residuals
            bias = bias + self.walk.offsets(self.y_g - b_g - np.outer(self.dT, k_g))
        return turn_rotations((self.rate - bias[:, None, :]) @ M_g.T, self.dt)

    def _turn_res(self, R: np.ndarray, u: np.ndarray) -> np.ndarray:
        d = carry(R, u[self.p]) - u[self.q]
        return np.einsum("mab,mib,mi->ma", self.W_t, self.B[self.q], d)

    def _gyro_rest_res(self, b_g: np.ndarray, k_g: np.ndarray) -> np.ndarray:
        e = self.y_g - b_g - np.outer(self.dT, k_g)
        if self.walk is not None:  # correlated through the walk: one (3n, 3n) whitener
            return self.walk.whitener @ e.ravel()
        return np.einsum("nij,nj->ni", self.W_g, e)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        S_a, b_a, M_g, b_g, k_a, k_g, v = self.unpack(x)
        u = v / np.linalg.norm(v, axis=1, keepdims=True)
        pred_a = self.g * u @ S_a.T + b_a + np.outer(self.dT, k_a)
        r_a = np.einsum("nij,nj->ni", self.W_a, self.y_a - pred_a)
        r_g = self._gyro_rest_res(b_g, k_g)
        r_t = self._turn_res(self._rotations(M_g, b_g, k_g), u)
        r_k = (np.concatenate([k_a, k_g]) - self.k0)[self.prior] * self.prior_w
        return np.concatenate([r_a.ravel(), r_g.ravel(), r_t.ravel(), r_k])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Dense (N, nm + 2n): analytic except the gyro columns (central differences)."""
        S_a, _, M_g, b_g, _, k_g, v = self.unpack(x)
        n, m, nm = self.n, len(self.p), self.nm
        nv = np.linalg.norm(v, axis=1)
        u = v / nv[:, None]
        # du/ddelta = (I - u u^T) B / |v|
        du = np.einsum("nij,njk->nik", np.eye(3) - np.einsum("ni,nj->nij", u, u), self.B) / nv[:, None, None]
        P = nm + 2 * n
        J = np.zeros((3 * n + 3 * n + 2 * m + len(self.prior), P))
        J_a = np.zeros((n, 3, P))
        J_a[:, :, :6] = -self.g * np.einsum("nij,kjl,nl->nik", self.W_a, _LOWER, u)
        J_a[:, :, 6:9] = -self.W_a
        idx = np.arange(n)
        blk = -self.g * np.einsum("nij,jk,nkl->nil", self.W_a, S_a, du)  # (n, 3, 2)
        for c in range(2):
            J_a[idx, :, nm + 2 * idx + c] = blk[:, :, c]
        J_g = np.zeros((n, 3, P))
        W_g = self.W_g
        if self.walk is not None:  # (3n, n, 3): the dense whitener's columns per rest
            W_g = self.walk.whitener.reshape(3 * n, n, 3)
            J_g = np.zeros((3 * n, P))
            J_g[:, 18:21] = -W_g.sum(axis=1)
        else:
            J_g[:, :, 18:21] = -W_g
        if self.fit_k:
            J_a[:, :, 21:24] = -self.W_a * self.dT[:, None, None]
            if self.walk is not None:
                J_g[:, 24:27] = -np.einsum("rnj,n->rj", W_g, self.dT)
            else:
                J_g[:, :, 24:27] = -W_g * self.dT[:, None, None]
        J[: 3 * n] = J_a.reshape(3 * n, P)
        J[3 * n: 6 * n] = J_g.reshape(3 * n, P)
        R = self._rotations(M_g, b_g, k_g)
        WE = np.einsum("mab,mib->mai", self.W_t, self.B[self.q])  # (m, 2, 3)
        J_t = np.zeros((m, 2, P))
        dp = np.einsum("mai,mji,mjk->mak", WE, R, du[self.p])
        dq = -np.einsum("mai,mik->mak", WE, du[self.q])
        jt = np.arange(m)
        for c in range(2):
            J_t[jt, :, nm + 2 * self.p + c] += dp[:, :, c]
            J_t[jt, :, nm + 2 * self.q + c] += dq[:, :, c]
        theta = np.concatenate([M_g.ravel(), b_g, k_g])
        cols = [(c, 9 + c) for c in range(12)] + ([(12 + c, 24 + c) for c in range(3)] if self.fit_k else [])
        for c, col in cols:
            h = 1e-6 * max(1.0, abs(theta[c]))
            res = []
            for sgn in (1.0, -1.0):
                t = theta.copy()
                t[c] += sgn * h
                res.append(self._turn_res(self._rotations(t[:9].reshape(3, 3), t[9:12], t[12:]), u))
            J_t[:, :, col] = (res[0] - res[1]) / (2 * h)
        J[6 * n: 6 * n + 2 * m] = J_t.reshape(2 * m, P)
        J[6 * n + 2 * m + np.arange(len(self.prior)), N_MAIN + self.prior] = self.prior_w
        return J

    # ------------------------------------------------------------------ output
    def output_jacobian(self, x: np.ndarray) -> np.ndarray:
        """(30, nm): d(M_a.ravel, b_a, M_g.ravel, b_g, k_a, k_g) / d(main parameters)."""
        S_a = self.unpack(x)[0]
        M_a = np.linalg.inv(S_a)
        G = np.zeros((N_OUT, self.nm))
        G[:9, :6] = -np.einsum("ij,kjl,lm->kim", M_a, _LOWER, M_a).reshape(6, 9).T
        G[9:12, 6:9] = np.eye(3)
        G[12:24, 9:21] = np.eye(12)
        if self.fit_k:
            G[24:30, 21:27] = np.eye(6)
        return G

    def covariance(self, x: np.ndarray) -> np.ndarray:
        """(30, 30) ``(J^T J)^-1`` at ``x`` marginalised over the rest directions, output layout."""
        J = self.jacobian(x)
        C = np.linalg.inv(J.T @ J)[: self.nm, : self.nm]
        G = self.output_jacobian(x)
        return G @ C @ G.T


def lower_gauge(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(L, Q)``: lower-triangular ``L`` and rotation ``Q`` with ``S = L Q`` (``L L^T = S S^T``)."""
    L = np.linalg.cholesky(S @ S.T)
    return L, np.linalg.solve(L, S)


def rotate_cov(cov: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Covariance (30, 30) of the output after ``M_a -> Q^T M_a``, ``M_g -> Q^T M_g``."""
    A = np.eye(N_OUT)
    K = np.kron(Q.T, np.eye(3))  # (Q^T M).ravel() = K M.ravel()
    A[:9, :9] = K
    A[12:21, 12:21] = K
    return A @ cov @ A.T


def fits_temperature(rests: Rests, setting: str) -> bool:
    """Whether to fit ``k``: ``yes``/``no``, or ``auto`` when the rests span MIN_SPREAD_C or more."""
    if setting != "auto":
        return setting == "yes"
    T = rests.temperature[np.isfinite(rests.temperature)]
    return len(T) > 0 and float(T.max() - T.min()) >= MIN_SPREAD_C


class JointML:
    """Solver ``joint_ml`` (kind ``joint``)."""

    name = "joint_ml"
    kind = "joint"
    version = "3"
    params: ClassVar[type[Params]] = JointMLParams

    def solve(self, observations: JointObservations, params: JointMLParams) -> JointFit:
        obs = observations
        used = ~saturated_turns(obs.turns, params.saturation_rad_s)[0]
        turns = drop_saturated(obs.turns, params.saturation_rad_s, "joint_ml")
        if len(turns) < 5 or len(obs.rests) < 9:
            raise SolverError(
                f"joint_ml: {len(obs.rests)} rests and {len(turns)} usable turns; the joint fit needs "
                "at least 9 rests and 5 turns about all three axes"
            )
        fit_k = fits_temperature(obs.rests, params.fit_temperature)
        S0, Q = lower_gauge(obs.accel.S)
        M_g0 = Q @ obs.gyro.M  # the gyro follows the accelerometer into the lower gauge
        sigma_k = np.concatenate([np.asarray(t.details.get("sigma_k", [np.inf] * 3), float)
                                  for t in (obs.accel, obs.gyro)])
        q, scatter = gyro_walk_intensity(obs.rests, obs.gyro, fit_k, params.gyro_bias_rw)
        walk = BiasWalk.build(obs.rests, turns, q)
        prob = JointProblem(obs.rests, turns, obs.gravity, S0, obs.accel.b0, M_g0, obs.gyro.b0,
                            obs.accel.k, obs.gyro.k, fit_k=fit_k, sigma_k=sigma_k, walk=walk)
        sol = least_squares(prob.residuals, prob.x0, jac=prob.jacobian, method="lm",
                            max_nfev=params.max_nfev, x_scale="jac")
        x = sol.x
        S_a, b_a, M_g, b_g, k_a, k_g, v = prob.unpack(x)
        u = v / np.linalg.norm(v, axis=1, keepdims=True)
        J = sol.jac
        JtJ = J.T @ J
        if np.linalg.cond(JtJ) > 1e14:
            raise SolverError(f"joint_ml: the rests and turns do not determine all {prob.nm} constants; "
                              "record rests over the whole sphere and turns about all three axes"
                              + (" (or set fit_temperature = 'no')" if fit_k else ""))
        C_all = np.linalg.inv(JtJ)
        C = C_all[: prob.nm, : prob.nm]
        G = prob.output_jacobian(x)
        cov = G @ C @ G.T
        chi2 = float(sol.fun @ sol.fun)
        dof = len(sol.fun) - len(x)
        inflation = max(1.0, chi2 / dof) if dof > 0 else 1.0
        cov = cov * inflation
        M_a = np.linalg.inv(S_a)
        R = prob._rotations(M_g, b_g, k_g)
        if params.keep_frame:
            M_a, M_g = Q.T @ M_a, Q.T @ M_g
            cov = rotate_cov(cov, Q)
            u = u @ Q  # Q^T u per row: gravity in the start's frame
        n = len(obs.rests)
        r = sol.fun
        blocks = block_statistics(r, J, C_all, n, len(turns))
        details = {
            "chi2": chi2, "dof": dof, "chi2_per_dof": chi2 / dof if dof > 0 else float("nan"),
            "inflation": inflation, "iterations": int(sol.nfev), "converged": bool(sol.success),
            "rms_whitened": {"accel": blocks["accel_rest"]["rms"], "gyro_rest": blocks["gyro_rest"]["rms"],
                             "turn": blocks["turn"]["rms"]},
            "blocks": blocks,
            "noise_model": ("white: each rest's own sample covariance over its count (rest means); "
                            "turns: the rests' median gyro sample covariance integrated over the turn "
                            "(sum dt^2); gyro bias random walk (intensity gyro_bias_walk.q): rest "
                            "means correlated, each turn's bias smoothed from the rests, its "
                            "uncertainty in the turn's noise; no accel bias drift, no earth rate"),
            "gyro_bias_walk": {"q": q.tolist(), "q_unit": "rad^2/s^3 per axis",
                               "sigma_rw": np.sqrt(q).tolist(), "sigma_rw_unit": "rad/s/sqrt(s)",
                               "estimated": scatter is not None,
                               "rest_scatter_sigma": None if scatter is None else float(np.sqrt(scatter)),
                               "rest_scatter_sigma_unit": "rad/s, rest-to-rest, not modelled"},
            "k_prior_entries": len(prob.prior),
            "turn_angle_deg_max": float(np.degrees(rotation_angle(R)).max()),
            "rests": n, "turns": len(turns), "turns_saturated": len(obs.turns) - len(turns),
            "fitted_temperature_coefficients": fit_k,
        }
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        triads = {
            "accel": TriadFit(M_a, b_a, cov[:12, :12], {"refined_by": "joint_ml"}),
            "gyro": TriadFit(M_g, b_g, cov[12:24, 12:24], {"refined_by": "joint_ml"}),
        }
        k = {"accel": np.asarray(k_a), "gyro": np.asarray(k_g)}
        sigma_k = {"accel": sd[24:27], "gyro": sd[27:30]} if fit_k else {}
        return JointFit(triads, cov, details, k, sigma_k, rest_gravity=u, turns_used=used)


def gyro_walk_intensity(rests: Rests, gyro: TriadCalibration, fit_k: bool,
                        sigma_rw: float | None) -> tuple[np.ndarray, float | None]:
    """(3,) gyro bias random-walk intensity, rad^2/s^3, and the rests' scatter beyond white
    noise without time correlation, (rad/s)^2 (None when not estimated): the configured
    ``sigma_rw`` (rad/s/sqrt(s)) squared, else REML from the rests' gyro means about the
    start's ``b0 + k dT`` (level, gravity direction, and ``dT`` when ``k`` is fitted,
    profiled out)."""
    if sigma_rw is not None:
        return np.full(3, float(sigma_rw) ** 2), None
    dT = np.where(np.isfinite(rests.temperature), rests.temperature, T_REF_C) - T_REF_C
    resid = rests.need("gyro") - gyro.bias(dT + T_REF_C)
    # an attitude effect (g-sensitivity) is a regressor, not a walk: the residuals keep showing it
    a = rests.need("accel")
    X = np.column_stack([np.ones(len(rests)), a / np.linalg.norm(a, axis=1, keepdims=True),
                         *([dT] if fit_k else [])])
    return estimate_intensity(rests, resid, X)


def block_statistics(r: np.ndarray, J: np.ndarray, C: np.ndarray, n: int, m: int) -> dict[str, dict]:
    """chi2, rows, effective dof and RMS of each block of the whitened residual ``r`` (N,).

    The effective dof of a block is its rows minus their leverages ``diag(J C J^T)``
    (``J`` (N, P) whitened Jacobian at the optimum, ``C = (J^T J)^-1``): the share of
    the fitted parameters (nuisance directions included) the block absorbs, so
    ``chi2 / dof`` is 1 in expectation per block when the model holds.
    """
    leverage = np.einsum("ip,pq,iq->i", J, C, J)
    edges = {"accel_rest": (0, 3 * n), "gyro_rest": (3 * n, 6 * n), "turn": (6 * n, 6 * n + 2 * m),
             "k_prior": (6 * n + 2 * m, len(r))}
    out = {}
    for name, (a, b) in edges.items():
        rows = b - a
        chi2 = float(r[a:b] @ r[a:b])
        dof = float(rows - leverage[a:b].sum())
        out[name] = {"chi2": chi2, "rows": rows, "dof": dof,  # None: undefined (JSON has no NaN)
                     "chi2_per_dof": chi2 / dof if dof > 0 else None,
                     "rms": float(np.sqrt(chi2 / rows)) if rows else None}
    return out


COMPONENTS = [JointML()]

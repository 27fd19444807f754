"""Joint maximum-likelihood refinement of accelerometer and gyroscope (beyond both papers).

One estimator over every rest and every turn, on the forward model of
``imupipe.diagnosis.forward`` (rest means and turn end-points): the unknowns are
the accelerometer's forward matrix ``S_a`` (lower-triangular: the accelerometer
frame is the reference, Eq. (1.3) of Chikrin & Golousov) and bias ``b_a``, the
gyroscope's correction ``M_g`` and bias ``b_g``, and, as nuisance parameters,
the true gravity direction at every rest. The measurements, each whitened by its
own noise::

    accel mean at rest i    y_a,i = S_a (g u_i) + b_a          cov: rest covariance / count
    gyro mean at rest i     y_g,i = b_g                        cov: rest covariance / count
    turn j from p to q      u_q = R_j(M_g, b_g)^T u_p          cov: integrated gyro noise

plus, when the rests span a range of temperatures, the bias temperature
coefficients ``k_a``, ``k_g`` (``+ k (T - 25)`` in every line above), so the
estimate is maximum likelihood, and its covariance is ``(J^T J)^-1`` of the
whitened Jacobian at the optimum with every nuisance marginalised (the
Cramer-Rao bound when evaluated at the truth). Both biases may also walk (a
Wiener process, ``solvers/brownian.py``): the intensities are estimated from the
rests (restricted likelihood, kept only when they beat the constant bias at 5 %
false alarms); the walks' states at the rests' boundaries are then nuisance
unknowns of the same fit, and ``b0`` is reported as the session's mean bias.
The earth's rotation is not in the model (15 deg/h; it biases ``b_g`` by its
projection). The normal matrix is block-tridiagonal in time, so the cost is
linear in the session's length.

It starts from any answer (method A's or B's). A start in another frame (not
lower-triangular) is moved to the lower-triangular gauge, refined, and turned
back, so the result keeps the frame convention of the start; the covariance is
then conditional on that frame (the accelerometer's axes are the gauge).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from ..components import Params
from ..errors import SolverError
from ..models import T_REF_C, TriadCalibration
from ..observations import Rests, TriadFit, Turns
from ..rotations import rotation_angle
from .brownian import MIN_LR, estimate_intensity
from .gyro_integration import drop_saturated, saturated_turns
from .triad_covariance import shape_basis

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
    accel_bias_rw: float | None = Field(None, ge=0)
    """Accelerometer bias random walk, m/s^2/sqrt(s), per axis; None: estimated from the rests'
    |g| errors (REML); 0: a constant bias."""


@dataclass(frozen=True)
class JointObservations:
    """What ``refine_joint`` hands to a ``joint`` solver.

    ``rests``/``turns`` as segmented (raw, sensor axes, SI); ``gravity`` the
    local magnitude m/s^2; ``accel``/``gyro`` the starting calibrations;
    ``temperature`` the session's temperature stream (seconds on the rests' clock,
    de-quantised: ``imupipe.temperature``), else the rests' own mean temperatures.
    """

    rests: Rests
    turns: Turns
    gravity: float
    accel: TriadCalibration
    gyro: TriadCalibration
    temperature: tuple[np.ndarray, np.ndarray] | None = None  # (t s, T degC) de-quantised


@dataclass(frozen=True)
class JointFit:
    """``triads``: refined ``TriadFit`` per sensor; ``cov`` (30, 30) over
    ``(M_a.ravel(), b_a, M_g.ravel(), b_g, k_a, k_g)`` (k rows zero when not fitted);
    ``details`` fit statistics; ``k`` the temperature coefficients used per sensor
    (fitted or the start's), ``sigma_k`` their 1-sigma when fitted; ``rest_gravity``
    (n, 3) the fitted unit gravity (nuisance) at every rest, instrument frame of the
    result; ``turns_used`` (m,) bool, the turns of the observations the fit used;
    ``linearised`` the fitted forward model (its rows and residuals, in the lower-triangular
    gauge) and ``frame`` the rotation ``Q`` from that gauge to the result's frame."""

    triads: dict[str, TriadFit]
    cov: np.ndarray
    details: dict[str, Any] = field(default_factory=dict)
    k: dict[str, np.ndarray] = field(default_factory=dict)
    sigma_k: dict[str, np.ndarray] = field(default_factory=dict)
    rest_gravity: np.ndarray | None = None
    turns_used: np.ndarray | None = None
    linearised: Any = None  # diagnosis.linearised.Linearised, in the lower-triangular gauge
    frame: np.ndarray | None = None  # (3, 3) Q: gauge -> the result's frame (u_result = Q^T u_gauge)


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


def _dT(rests: Rests) -> np.ndarray:
    return np.where(np.isfinite(rests.temperature), rests.temperature, T_REF_C) - T_REF_C


def gyro_walk_intensity(rests: Rests, gyro: TriadCalibration, fit_k: bool, sigma_rw: float | None,
                        min_lr: float = MIN_LR) -> tuple[np.ndarray, float | None]:
    """(3,) gyro bias random-walk intensity, rad^2/s^3, and the rests' scatter beyond white
    noise without time correlation, (rad/s)^2 (None when not estimated): the configured
    ``sigma_rw`` (rad/s/sqrt(s)) squared, else REML from the rests' gyro means about the
    start's ``b0 + k dT`` (level, gravity direction, ``dT`` when ``k`` is fitted, and ``dT^2``
    profiled out).

    ``dT^2``: a bias law left out of the model is deterministic; taken as walk intensity it hides
    itself (the walk copies it for free) from the residual map and the diagnosis that look for
    it. Where profiling it leaves no walk at all, the walk's own evidence was the slow part the
    law took (a walk and a smooth law are not told apart over a few long rests), and the estimate
    without it stands: a walk set to zero would flag its own wander as misfit. ``min_lr``: the
    detection's threshold (``brownian.estimate_intensity``)."""
    if sigma_rw is not None:
        return np.full(3, float(sigma_rw) ** 2), None
    dT = _dT(rests)
    resid = rests.need("gyro") - gyro.bias(dT + T_REF_C)
    # an attitude effect (g-sensitivity) is a regressor, not a walk: the residuals keep showing it
    a = rests.need("accel")
    X = np.column_stack([np.ones(len(rests)), a / np.linalg.norm(a, axis=1, keepdims=True),
                         *([dT] if fit_k else [])])
    var = np.diagonal(rests.cov_of_mean("gyro"), axis1=1, axis2=2)
    q, nu = estimate_intensity(rests.t_start_s, rests.t_end_s, resid, var, np.column_stack([X, dT ** 2]),
                               min_lr=min_lr)
    if q == 0:
        q, nu = estimate_intensity(rests.t_start_s, rests.t_end_s, resid, var, X, min_lr=min_lr)
    return np.full(3, q), nu


def accel_walk_intensity(rests: Rests, accel: TriadCalibration, gravity: float, fit_k: bool,
                         sigma_rw: float | None, min_lr: float = MIN_LR) -> np.ndarray:
    """(3,) accelerometer bias random-walk intensity, (m/s^2)^2/s per axis (isotropic): the
    configured ``sigma_rw`` squared, else REML from the rests' |g| errors under the start
    (a walk shows along gravity only: the tilt part is each rest's unknown direction), with
    the accelerometer's own parameters (and ``dT`` when ``k`` is fitted) profiled out. Not each
    axis's ``dT^2`` as for the gyro: seen along gravity only, the walk's evidence is too thin for
    three more columns (six with a warm-up took it whole on a gimbal null)."""
    if sigma_rw is not None:
        return np.full(3, float(sigma_rw) ** 2)
    dT = _dT(rests)
    y = rests.need("accel")

    def norm_error(theta: np.ndarray) -> np.ndarray:
        M, b = theta[:9].reshape(3, 3), theta[9:12]
        k = theta[12:15] if fit_k else accel.k
        return np.linalg.norm((y - b - np.outer(dT, k)) @ M.T, axis=1) - gravity

    theta = np.concatenate([accel.M.ravel(), accel.b0, *([accel.k] if fit_k else [])])
    r = norm_error(theta)
    X = np.empty((len(y), len(theta)))
    for c in range(len(theta)):  # the regressors: what the accelerometer's own fit absorbs
        h = 1e-7 * max(1.0, abs(theta[c]))
        d = np.zeros(len(theta))
        d[c] = h
        X[:, c] = (norm_error(theta + d) - norm_error(theta - d)) / (2 * h)
    x = (y - accel.bias(dT + T_REF_C)) @ accel.M.T
    u = x / np.linalg.norm(x, axis=1, keepdims=True)
    H = u @ accel.M  # the walk, in raw axes, seen along gravity
    var = np.einsum("ni,nij,nj->n", H, rests.cov_of_mean("accel"), H)
    q, _ = estimate_intensity(rests.t_start_s, rests.t_end_s, r[:, None], var[:, None], X, H, min_lr=min_lr)
    return np.full(3, q)


class JointML:
    """Solver ``joint_ml`` (kind ``joint``)."""

    name = "joint_ml"
    kind = "joint"
    version = "6"
    params: ClassVar[type[Params]] = JointMLParams

    def solve(self, observations: JointObservations, params: JointMLParams) -> JointFit:
        from ..diagnosis.attitude import Attitude
        from ..diagnosis.linearised import fit

        obs = observations
        used = ~saturated_turns(obs.turns, params.saturation_rad_s)[0]
        model, Q, (q_a, q_g, scatter) = joint_model(obs, params)
        turns = model.turns
        fit_k = model.fit_k
        lin = fit(model, max_iter=params.max_nfev)
        blocks = lin.blocks()
        d = np.sqrt(np.clip(np.diag(lin.system.S), 1e-300, None))  # scale-free: raw counts are units too
        if np.linalg.cond(lin.system.S / np.outer(d, d)) > 1e14:
            raise SolverError(f"joint_ml: the rests and turns do not determine all {model.glob.size} "
                              "constants; record rests over the whole sphere and turns about all three axes"
                              + (" (or set fit_temperature = 'no')" if fit_k else ""))
        P = model.unpack(lin.x_g)
        # report each bias as the session's mean (the walks are pinned at the first rest)
        mean_a, mean_g, L = walk_means(model)
        b_a = P["b_a"] + (mean_a @ lin.x_l if "wa" in model.walks else 0.0)
        b_g = P["b_g"] + (mean_g @ lin.x_l if "wg" in model.walks else 0.0)
        cov = output_covariance(lin, P, mean_a if "wa" in model.walks else None,
                                mean_g if "wg" in model.walks else None)
        chi2, dof = lin.chi2, lin.dof
        inflation = max(1.0, chi2 / dof) if dof > 0 else 1.0
        cov = cov * inflation
        M_a, M_g = np.linalg.inv(P["S_a"]), P["M_g"]
        u = model.gravity(lin.x_l)[0]
        omega, _ = model._rates(P, lin.x_l, derivatives=False)
        R = Attitude.integrate(model.quad, omega).total
        if params.keep_frame:
            M_a, M_g = Q.T @ M_a, Q.T @ M_g
            cov = rotate_cov(cov, Q)
            u = u @ Q  # Q^T u per row: gravity in the start's frame
        details = {
            "chi2": chi2, "dof": dof, "chi2_per_dof": chi2 / dof if dof > 0 else float("nan"),
            "inflation": inflation, "iterations": int(lin.iterations), "converged": bool(lin.converged),
            "rms_whitened": {k: b["rms"] for k, b in blocks.items()},
            "blocks": blocks,
            "gauge": ("accelerometer frame: its lower-triangular S_a fixes the instrument axes; "
                      "covariances are conditional on that frame" + (" (turned back to the start's frame)"
                                                                    if params.keep_frame else "")),
            "noise_model": ("white: each rest's own sample covariance over its count (rest means); "
                            "turns: the rests' median gyro sample covariance integrated over the turn; "
                            "gyro and accelerometer bias random walks (intensities gyro_bias_walk.q, "
                            "accel_bias_walk.q): their states at the rests' boundaries fitted with "
                            "Brownian increments; no earth rate"),
            "gyro_bias_walk": {"q": q_g.tolist(), "q_unit": "rad^2/s^3 per axis",
                               "sigma_rw": np.sqrt(q_g).tolist(), "sigma_rw_unit": "rad/s/sqrt(s)",
                               "estimated": params.gyro_bias_rw is None,
                               "rest_scatter_sigma": None if scatter is None else float(np.sqrt(scatter)),
                               "rest_scatter_sigma_unit": "rad/s, rest-to-rest, not modelled"},
            "accel_bias_walk": {"q": q_a.tolist(), "q_unit": "(m/s^2)^2/s per axis",
                                "sigma_rw": np.sqrt(q_a).tolist(), "sigma_rw_unit": "m/s^2/sqrt(s)",
                                "estimated": params.accel_bias_rw is None},
            "k_prior_entries": len(model.k_prior), "gravity_m_s2": float(obs.gravity),
            "turn_angle_deg_max": float(np.degrees(rotation_angle(R)).max()) if len(R) else 0.0,
            "rests": len(obs.rests), "turns": len(turns), "turns_saturated": len(obs.turns) - len(turns),
            "fitted_temperature_coefficients": fit_k,
        }
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        triads = {
            "accel": TriadFit(M_a, b_a, cov[:12, :12], {"refined_by": "joint_ml"}),
            "gyro": TriadFit(M_g, b_g, cov[12:24, 12:24], {"refined_by": "joint_ml"}),
        }
        k = {"accel": np.asarray(P["k_a"]), "gyro": np.asarray(P["k_g"])}
        sigma_k = {"accel": sd[24:27], "gyro": sd[27:30]} if fit_k else {}
        return JointFit(triads, cov, details, k, sigma_k, rest_gravity=u, turns_used=used,
                        linearised=lin, frame=Q if params.keep_frame else np.eye(3))


def joint_model(obs: JointObservations, params: JointMLParams):
    """The forward model (rest means and turn end-points) of ``obs`` started at its calibrations,
    in the lower-triangular gauge: ``(model, Q, (q_accel, q_gyro, gyro rest scatter))`` with ``Q``
    the rotation from the gauge back to the start's frame."""
    from ..diagnosis.forward import JointModel, Noise, Start

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
    q_g, scatter = gyro_walk_intensity(obs.rests, obs.gyro, fit_k, params.gyro_bias_rw)
    q_a = accel_walk_intensity(obs.rests, obs.accel, obs.gravity, fit_k, params.accel_bias_rw)
    noise = Noise.from_rests(obs.rests, q_a, q_g)
    start = Start(S0, obs.accel.b0, M_g0, obs.gyro.b0, obs.accel.k, obs.gyro.k, sigma_k)
    model = JointModel(obs.rests, turns, obs.gravity, start, noise, fit_k=fit_k, temperature=obs.temperature)
    return model, Q, (q_a, q_g, scatter)


def covariance_at_start(obs: JointObservations, params: JointMLParams) -> np.ndarray:
    """(30, 30) output covariance of the joint model linearised at its start, in the start's frame:
    at the truth, the Cramer-Rao bound of the rests and turns."""
    from ..diagnosis.linearised import fit

    model, Q, _ = joint_model(obs, params)
    lin = fit(model, max_iter=0)
    P = model.unpack(lin.x_g)
    mean_a, mean_g, _ = walk_means(model)
    cov = output_covariance(lin, P, mean_a if "wa" in model.walks else None,
                            mean_g if "wg" in model.walks else None)
    return rotate_cov(cov, Q) if params.keep_frame else cov


def walk_means(model) -> tuple[np.ndarray, np.ndarray, float]:
    """(3, P_l) maps from the locals to each walk's mean over the session (accel, gyro), and the
    session's length: the interpolated path between the boundary states, averaged."""
    out = {}
    rs = model.rests
    t0, t1 = float(rs.t_start_s.min()), float(rs.t_end_s.max())
    L = max(t1 - t0, 1e-12)
    for w in ("wa", "wg"):
        A = np.zeros((3, model.stages.size))
        if w in model.walks:
            a, b = model.stages.walk_cols[w]
            times = []  # (state column or -1, time) in time order
            for i in range(model.n):
                times.append((a[i], rs.t_start_s[i]))
                times.append((b[i], rs.t_end_s[i]))
            for (c0, s0), (c1, s1) in zip(times[:-1], times[1:], strict=True):
                w_len = 0.5 * (s1 - s0) / L  # trapezoid of the linear path between the states
                for c in (c0, c1):
                    if c >= 0:
                        A[np.arange(3), c + np.arange(3)] += w_len
        out[w] = A
    return out["wa"], out["wg"], L


def output_covariance(lin, P: dict, mean_a: np.ndarray | None, mean_g: np.ndarray | None) -> np.ndarray:
    """(30, 30) covariance of ``(M_a.ravel(), b_a, M_g.ravel(), b_g, k_a, k_g)`` (k rows zero when
    not fitted), the biases as session means: a linear map of the globals and locals."""
    model = lin.model
    gl = model.glob.slices
    Pg, Pl = model.glob.size, model.stages.size
    M_a = np.linalg.inv(P["S_a"])
    G = np.zeros((N_OUT, Pg))
    G[:9, gl["S_a"]] = -np.einsum("ij,kjl,lm->kim", M_a, _LOWER, M_a).reshape(6, 9).T
    G[9:12, gl["b_a"]] = np.eye(3)
    G[12:21, gl["M_g"]] = np.eye(9)
    G[21:24, gl["b_g"]] = np.eye(3)
    if model.fit_k:
        G[24:27, gl["k_a"]] = np.eye(3)
        G[27:30, gl["k_g"]] = np.eye(3)
    Lm = np.zeros((N_OUT, Pl))
    if mean_a is not None:
        Lm[9:12] = mean_a
    if mean_g is not None:
        Lm[21:24] = mean_g
    cov = lin.variance_of(G, Lm)
    return 0.5 * (cov + cov.T)


COMPONENTS = [JointML()]

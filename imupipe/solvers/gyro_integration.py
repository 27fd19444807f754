"""Gyroscope, method B (Chikrin & Golousov 2021): fit by integrating the turns.

The bias is the mean rate over the rests, Eq. (2.14)-(2.15). The remaining nine
constants ``theta`` (scales and the full misalignment, Eq. (1.5)) minimise the
mismatch between the gravity direction measured at the rest after each turn
and the one measured before it, carried through the turn by the integrated,
corrected gyro, Eq. (2.16)-(2.18), starting from the ideal sensor
``theta_0 = [1, 1, 1, 0, ...]``.

imupipe parametrises the nine constants as the correction matrix ``M``
(``omega = M (omega_raw - b)``), which spans the same set as ``(M^G S^G)^-1``;
``M`` starts at the identity. Gravity directions come from the corrected
accelerometer, so ``M`` also carries the gyro-to-accelerometer alignment: the
gyro ends up in the accelerometer's frame. Rotations are integrated exactly
(``imupipe.rotations``), all turns at once.
"""

from __future__ import annotations

import itertools
import warnings
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from ..components import Params
from ..diagnosis.events import clipped
from ..errors import SolverError
from ..observations import GyroObservations, TriadFit, Turns
from ..rotations import carry, pad_turns, turn_rotations
from .levenberg_marquardt import levenberg_marquardt
from .triad_covariance import gauss_newton_cov

MIN_TURNS = 5  # each turn gives two equations for nine constants


class GyroIntegrationParams(Params):
    bias: Literal["all_rests", "adjacent_rests", "first_rest"] = "all_rests"
    """all_rests: one bias, the mean over every rest (Eq. (2.15)); adjacent_rests: each turn
    uses the mean of the rests before and after it (a bias that wanders between rests);
    first_rest: the first rest's mean (imu_tk's initial static interval)."""
    fit_bias: bool = False
    """Also refine the bias in the optimisation (the paper keeps Eq. (2.15)'s mean)."""
    max_nfev: int = Field(200, ge=1)
    """Cost evaluations the optimiser may spend, its difference Jacobians' included."""
    exclude_saturated: bool = True
    """Leave out turns whose gyro clips (runs of samples at the axis's extreme value, or
    beyond ``saturation_rad_s``), with a warning: a clipped rate cannot be integrated."""
    saturation_rad_s: float | None = Field(None, gt=0)
    """The gyro's range in rad/s when known; None: detect clipping from the data."""
    scale_search: bool = True
    """Start from the best ``s I`` on a grid around the turn angles implied by gravity (the
    paper's ``theta_0 = I`` only works for readings already near SI; raw counts need this)."""


def rest_bias(bias: np.ndarray, bias_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (2.15) over all rests, inverse-variance weighted: mean (3,) rad/s and its (3, 3) covariance.

    ``bias`` (n, 3) rest means, ``bias_cov`` (n, 3, 3) their covariances.
    """
    w = 1.0 / np.maximum(np.trace(bias_cov, axis1=1, axis2=2), 1e-300)
    w = w / w.sum()
    mean = w @ bias
    cov = np.einsum("n,nij->ij", w**2, bias_cov)
    return mean, cov


def saturated_turns(turns: Turns, limit: float | None = None) -> tuple[np.ndarray, int, list[str]]:
    """Turns holding clipped gyro samples (``events.clipped``): mask (m,), the number of such
    samples, the axes."""
    if not len(turns):
        return np.zeros(0, bool), 0, []
    flag = clipped(np.concatenate(turns.gyro), limit)
    bounds = np.cumsum([0] + [len(g) for g in turns.gyro])
    per_turn = np.array([flag[a:b].any() for a, b in itertools.pairwise(bounds)])
    axes = [a for a, f in zip("xyz", flag.any(axis=0), strict=True) if f]
    return per_turn, int(flag.any(axis=1).sum()), axes


def drop_saturated(turns: Turns, limit: float | None, who: str) -> Turns:
    """``turns`` without the clipped ones, warning how many were left out."""
    bad, n_samples, axes = saturated_turns(turns, limit)
    if bad.any():
        warnings.warn(f"{who}: {int(bad.sum())} of {len(turns)} turns hold {n_samples} saturated gyro "
                      f"samples (axes {', '.join(axes)}); those turns are left out", stacklevel=3)
        return turns.subset(~bad)
    return turns


def initial_scale(rate: np.ndarray, dt: np.ndarray, g0: np.ndarray, g1: np.ndarray,
                  cost) -> tuple[float, np.ndarray]:
    """Best ``s`` for ``M = s I`` and its grid: around the median ratio of the gravity angle
    (a lower bound of each turn's angle) to the raw integrated angle, over the tilting turns."""
    tilt = np.arccos(np.clip(np.sum(g0 * g1, axis=1), -1, 1))
    raw = np.linalg.norm(np.einsum("mk,mki->mi", dt, rate), axis=1)
    use = (tilt > np.radians(5.0)) & (raw > 0)
    s0 = float(np.median(tilt[use] / raw[use])) if use.any() else 1.0
    grid = s0 * np.geomspace(0.5, 4.0, 25)
    costs = [float(np.sum(cost(s * np.eye(3).ravel()) ** 2)) for s in grid]
    return float(grid[int(np.argmin(costs))]), grid


def gravity_residuals(M: np.ndarray, b: np.ndarray, rate: np.ndarray, dt: np.ndarray,
                      g_before: np.ndarray, g_after: np.ndarray) -> np.ndarray:
    """(m, 3) ``R_j^T g_before - g_after`` of Eq. (2.18) for padded turns.

    ``rate`` (m, k, 3) raw rad/s, ``dt`` (m, k) s, ``g_*`` (m, 3) unit vectors.
    """
    return carry(turn_rotations(rate - b, dt, M), g_before) - g_after


class GyroIntegration:
    """Solver ``gyro_integration`` (kind ``gyro``): Eq. (2.15)-(2.18) by least squares."""

    name = "gyro_integration"
    kind = "gyro"
    version = "2"  # 2: imupipe's own Levenberg-Marquardt (was scipy's MINPACK)
    params: ClassVar[type[Params]] = GyroIntegrationParams

    def solve(self, observations: GyroObservations, params: GyroIntegrationParams) -> TriadFit:
        turns = observations.turns
        n_all = len(turns)
        if params.exclude_saturated:
            turns = drop_saturated(turns, params.saturation_rad_s, "gyro_integration")
        m = len(turns)
        if m < MIN_TURNS:
            left = f" ({n_all - m} left out as saturated)" if m < n_all else ""
            raise SolverError(
                f"gyro_integration: {m} usable turns between rests{left} for 9 gyroscope constants; "
                f"record at least {MIN_TURNS - m} more turns (about all three axes)"
            )
        gravity = np.asarray(observations.gravity, float)
        gravity = gravity / np.linalg.norm(gravity, axis=1, keepdims=True)
        g0, g1 = gravity[turns.before], gravity[turns.after]
        rate, dt = pad_turns(turns.t, turns.gyro)
        b, b_cov = rest_bias(np.asarray(observations.bias, float),
                             np.asarray(observations.bias_cov, float))
        if params.bias == "first_rest":
            b, b_cov = np.asarray(observations.bias, float)[0], np.asarray(observations.bias_cov, float)[0]

        def unpack(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return theta[:9].reshape(3, 3), (theta[9:] if params.fit_bias else b)

        if params.bias == "adjacent_rests" and not params.fit_bias:
            rb = np.asarray(observations.bias, float)
            rate_c = rate - 0.5 * (rb[turns.before] + rb[turns.after])[:, None, :]
        else:
            rate_c = rate - b  # bias of Eq. (2.15) removed once when it is not refined

        def cost(theta: np.ndarray) -> np.ndarray:
            M, bias = unpack(theta)
            if params.fit_bias:
                return gravity_residuals(M, bias, rate, dt, g0, g1).ravel()  # Eq. (2.18)
            return gravity_residuals(M, 0.0, rate_c, dt, g0, g1).ravel()

        scale = 1.0
        if params.scale_search:
            scale, _ = initial_scale(rate_c, dt, g0, g1, lambda th: cost(np.concatenate(
                [th, b if params.fit_bias else []])))
        theta0 = np.concatenate([scale * np.eye(3).ravel(), b if params.fit_bias else []])
        sol = levenberg_marquardt(cost, theta0, params.max_nfev)
        M, bias = unpack(sol.x)
        J = sol.jac
        if np.linalg.matrix_rank(J.T @ J, tol=1e-10 * np.abs(J.T @ J).max()) < len(theta0):
            raise SolverError(
                "gyro_integration: the turns do not determine all nine gyroscope constants; "
                "record turns about all three axes (and combinations of them)"
            )
        ssr = float(sol.fun @ sol.fun)
        dof = 2 * m - len(theta0)  # the along-gravity residual component is second order
        if dof > 0:  # noise level from the residuals themselves
            cov_p, _ = gauss_newton_cov(J * np.sqrt(dof / ssr), 0.0, dof)
        else:  # as many constants as equations: no honest uncertainty
            cov_p = np.full((len(theta0), len(theta0)), np.nan)
        cov12 = np.full((12, 12), np.nan)
        cov12[:9, :9] = cov_p[:9, :9]
        cov12[9:, 9:] = cov_p[9:, 9:] if params.fit_bias else b_cov
        if params.fit_bias:
            cov12[:9, 9:] = cov_p[:9, 9:]
            cov12[9:, :9] = cov_p[9:, :9]
        else:
            cov12[:9, 9:] = cov12[9:, :9] = 0.0
        res_deg = np.degrees(np.linalg.norm(sol.fun.reshape(m, 3), axis=1))
        details = {
            "turns": m,
            "turns_saturated": n_all - m,
            "rms_gravity_mismatch_deg": float(np.sqrt(np.mean(res_deg**2))),
            "max_gravity_mismatch_deg": float(res_deg.max()),
            "cost_evaluations": int(sol.nfev),
            "converged": bool(sol.success),
            "fit_bias": params.fit_bias,
            "bias_model": "fitted" if params.fit_bias else params.bias,
            "initial_scale": scale,
        }
        return TriadFit(M, bias, cov12, details)


COMPONENTS = [GyroIntegration()]

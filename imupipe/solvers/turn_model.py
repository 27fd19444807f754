"""The gravity mismatch after a turn under an accel + gyro calibration, and its noise model.

For a turn from rest ``p`` to rest ``q`` the calibrated gyro, integrated over the
motion, gives the rotation ``R`` (body at the end -> body at the start); gravity
measured at ``p`` carried through it should be gravity measured at ``q``::

    d = R^T u_p - u_q                                   Chikrin & Golousov, Eq. (2.16)

This is the turn term of the joint likelihood (``joint_ml``). Its noise: the
white gyro noise of one sample, integrated over the turn (``sum dt^2 M Sigma_g
M^T``, rad^2), and the white noise of the two rests' accelerometer means carried
to unit directions. Only the part of ``d`` normal to ``u_q`` is informative
(two components), so the whitened mismatch is 2-dimensional: ``chi2 = |w|^2`` has
2 degrees of freedom per turn when the model holds. Frame: the instrument frame
of the calibration (``apply``). Derivation: docs/method-b.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..models import T_REF_C, TriadCalibration
from ..observations import Rests, Turns
from ..rotations import carry, pad_turns, rotation_angle, skew, turn_rotations
from .bias_walk import BiasWalk, rest_intervals, turn_intervals


def tangent_basis(u: np.ndarray) -> np.ndarray:
    """(n, 3, 2) orthonormal bases of the planes normal to unit vectors ``u`` (n, 3)."""
    helper = np.where(np.abs(u[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return np.stack([e1, e2], axis=-1)


def gyro_sample_cov(rests: Rests) -> np.ndarray:
    """(3, 3) covariance of one raw gyro sample, (rad/s)^2: the median over the rests."""
    return np.median(rests.cov["gyro"], axis=0)


def integrated_gyro_cov(sigma_g: np.ndarray, dt: np.ndarray, M_g: np.ndarray) -> np.ndarray:
    """(m, 3, 3) covariance, rad^2, of the rotation vector of padded turns (``dt`` (m, k) s)
    from white noise ``sigma_g`` (3, 3) (rad/s)^2 per raw sample, calibrated by ``M_g``."""
    return np.sum(dt**2, axis=1)[:, None, None] * (M_g @ sigma_g @ M_g.T)


def carried_cov(v: np.ndarray, cov_phi: np.ndarray) -> np.ndarray:
    """(m, 3, 3) covariance of a carried unit vector ``v`` (m, 3) from rotation noise ``cov_phi``."""
    Vx = skew(v)
    return Vx @ cov_phi @ np.swapaxes(Vx, -1, -2)


def model_temperature(T: np.ndarray) -> np.ndarray:
    """Temperatures for the models: unknown (NaN) is taken as the reference (no thermal term)."""
    return np.where(np.isfinite(T), T, T_REF_C)


def turn_temperature(rests: Rests, turns: Turns) -> np.ndarray:
    """(m,) degC at each turn: its two rests' mean temperatures interpolated in time to the
    turn's midpoint (a long warm-up rest's mean is not its temperature at the end); unknown
    (NaN) is the reference."""
    T = model_temperature(rests.temperature)
    p, q = np.asarray(turns.before), np.asarray(turns.after)
    mid, _ = rest_intervals(rests)
    t_turn, _ = turn_intervals(rests, turns)
    span = mid[q] - mid[p]
    w = np.clip(np.divide(t_turn - mid[p], span, out=np.full(len(p), 0.5), where=span > 0), 0, 1)
    return T[p] + w * (T[q] - T[p])


def gravity_directions(rests: Rests, accel: TriadCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Unit gravity (n, 3) at every rest from the calibrated accel means, and its covariance
    (n, 3, 3) from the white noise of each mean (first order: ``(I - u u^T) M / |x|``)."""
    x = accel.apply(rests.need("accel"), model_temperature(rests.temperature))
    nx = np.linalg.norm(x, axis=1)
    u = x / nx[:, None]
    P = (np.eye(3) - np.einsum("ni,nj->nij", u, u)) / nx[:, None, None]
    A = P @ accel.M
    return u, A @ rests.cov_of_mean("accel") @ np.swapaxes(A, -1, -2)


@dataclass(frozen=True)
class TurnMismatch:
    """The mismatch of m turns; unit vectors in the instrument frame (differences ~ rad).

    ``predicted`` (m, 3) gravity before carried through the calibrated turn; ``measured``
    (m, 3) gravity after; ``residual`` = measured - predicted; ``whitened`` (m, 2) its
    components normal to ``measured`` whitened by the modelled covariance ``cov`` (m, 2, 2)
    rad^2; ``sigma_gyro``/``sigma_rests`` (m,) rad, RMS 1-sigma per component of the
    integrated gyro noise and of the rests' noise; ``angle`` (m,) rad, the calibrated turn.
    """

    predicted: np.ndarray
    measured: np.ndarray
    residual: np.ndarray
    whitened: np.ndarray
    cov: np.ndarray
    sigma_gyro: np.ndarray
    sigma_rests: np.ndarray
    angle: np.ndarray

    @property
    def chi2(self) -> np.ndarray:
        """(m,) squared whitened mismatch, 2 degrees of freedom each."""
        return np.sum(self.whitened**2, axis=1)


def turn_mismatch(rests: Rests, turns: Turns, accel: TriadCalibration,
                  gyro: TriadCalibration, bias_walk_q: np.ndarray | None = None) -> TurnMismatch:
    """Every turn's gravity mismatch under ``accel``/``gyro`` (any method's calibration).

    Each turn's gyro bias is taken at its temperature (``turn_temperature``), as in the
    joint likelihood; the gyro noise is the rests' median (``gyro_sample_cov``). With a
    bias random walk ``bias_walk_q`` (3,) rad^2/s^3, each turn's bias also carries the walk
    smoothed from the rests' gyro means, and its uncertainty joins the gyro noise.
    """
    u, cov_u = gravity_directions(rests, accel)
    p, q = np.asarray(turns.before), np.asarray(turns.after)
    rate, dt = pad_turns(turns.t, turns.gyro)
    bias = gyro.bias(turn_temperature(rests, turns))  # (m, 3)
    cov_phi = integrated_gyro_cov(gyro_sample_cov(rests), dt, gyro.M)
    walk = BiasWalk.build(rests, turns, np.zeros(3) if bias_walk_q is None else bias_walk_q)
    if walk.active:
        bias = bias + walk.offsets(rests.need("gyro") - gyro.bias(model_temperature(rests.temperature)))
        cov_phi = cov_phi + walk.rotation_cov(dt.sum(axis=1), gyro.M)
    R = turn_rotations((rate - bias[:, None, :]) @ gyro.M.T, dt)
    v = carry(R, u[p])
    d = u[q] - v
    cov_g = carried_cov(v, cov_phi)
    cov_r = np.swapaxes(R, -1, -2) @ cov_u[p] @ R + cov_u[q]
    E = tangent_basis(u[q])
    Et = np.swapaxes(E, -1, -2)
    cov2_g, cov2_r = Et @ cov_g @ E, Et @ cov_r @ E
    cov2 = cov2_g + cov2_r + 1e-30 * np.eye(2)
    L = np.linalg.cholesky(cov2)
    w = np.linalg.solve(L, np.einsum("mai,mi->ma", Et, d)[..., None])[..., 0]

    def rms_sigma(c: np.ndarray) -> np.ndarray:
        return np.sqrt(np.trace(c, axis1=1, axis2=2) / 2)

    return TurnMismatch(v, u[q], d, w, cov2, rms_sigma(cov2_g), rms_sigma(cov2_r), rotation_angle(R))

"""The magnetometer in the residual map: what its calibration predicts at every rest.

A rest fixes the gravity direction but not the heading, so the calibrated field of rest
``i``, ``h_i``, is predicted up to a rotation about gravity: its magnitude is the
session's field ``F`` and its angle to gravity is the dip. Two residuals per rest are
heading-free and carry every error of the magnetometer's calibration and of its physics
(hard and soft iron left, a field gradient across rest positions, interference from
currents): ``|h_i| - F`` and the dip difference times ``F``, each whitened by the rest
mean's covariance (the segmentation's, with the rest's effective sample size) pushed
through the calibration. The calibration (M, b0 and k where the rests span 1 degC) and the
dip are refitted to these rows (``F`` is the rests' mean: M carries the scale), and each row counts one minus its leverage.

Within-rest scatter is tested against the sensor's noise from successive differences
(white noise and quantisation pass through them; an interference of ~1 Hz, slow
wander or a vibrating support do not), per rest and axis.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ..models import TriadCalibration
from ..observations import Rests
from .residual_map import RowSet, _gravity_cell

def rest_rows(rests: Rests, accel: TriadCalibration, mag: TriadCalibration) -> RowSet | None:
    """Magnitude and dip rows of every rest (axis -1: they belong to no single axis), with the
    magnetometer's calibration refitted to them (as the map judges the model, not the estimation
    error of a calibration fitted to fewer or differently weighted data)."""
    if not rests.has("mag") or len(rests) < 3:
        return None
    T = np.where(np.isfinite(rests.temperature), rests.temperature, 25.0)
    dT = T - 25.0
    u = accel.apply(rests.mean["accel"], T)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    y = rests.mean["mag"]
    cov = rests.cov_of_mean("mag")
    thermal = bool(np.ptp(dT) >= 1.0)

    h0 = mag.apply(y, T)
    n0 = np.linalg.norm(h0, axis=1)
    F = float(np.mean(n0))  # the scale's gauge: M carries it

    def unpack(th):
        return th[:9].reshape(3, 3), th[9:12], th[12:15] if thermal else np.zeros(3), th[-1]

    def residual(th, sigmas=None):
        M, b, k, dip = unpack(th)
        h = (y - b - np.outer(dT, k)) @ M.T
        n = np.linalg.norm(h, axis=1)
        hx = h / n[:, None]
        c = np.clip(np.sum(hx * u, axis=1), -1, 1)
        if sigmas is None:
            C = np.einsum("ij,njk,lk->nil", M, cov, M)
            e = u - c[:, None] * hx  # in the plane of h and gravity, across h: where the dip moves h
            e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-12)
            sigmas = (np.sqrt(np.einsum("ni,nij,nj->n", hx, C, hx)), np.sqrt(np.einsum("ni,nij,nj->n", e, C, e)))
        return np.concatenate([(n - F) / sigmas[0], (np.arcsin(c) - dip) * F / sigmas[1]]), sigmas

    th0 = np.concatenate([mag.M.ravel(), mag.b0, *([mag.k] if thermal else []),
                          [np.mean(np.arcsin(np.clip(np.sum(h0 / n0[:, None] * u, 1), -1, 1)))]])
    _, sigmas = residual(th0)
    fit = least_squares(lambda th: residual(th, sigmas)[0], th0, x_scale="jac", method="lm")
    r = fit.fun
    # each row's degrees of freedom: one minus its leverage under the refit (rank-aware)
    U, sv, _ = np.linalg.svd(fit.jac, full_matrices=False)
    U = U[:, sv > 1e-9 * sv.max()]
    w = np.clip(1 - np.sum(U ** 2, axis=1), 1e-3, 1)
    mid = 0.5 * (rests.t_start_s + rests.t_end_s)
    t = np.tile(mid, 2)
    k = len(rests)
    var = {"temperature degC": np.tile(rests.temperature, 2), "gravity along": np.tile(_gravity_cell(u), 2).astype(float),
           "time s": t}
    return RowSet(r, w, np.full(2 * k, "mag"), np.full(2 * k, -1), np.full(2 * k, "static"), t, var)


def scatter_rows(rests: Rests, t_s: np.ndarray, y: np.ndarray) -> RowSet | None:
    """Within-rest scatter of the raw magnetometer against its successive-difference noise:
    one row per rest and axis with ``r^2 = (m - 1) s^2 / sigma^2`` on ``m - 1`` dof."""
    if not len(t_s) or not len(rests):
        return None
    lo = np.searchsorted(t_s, rests.t_start_s, "left")
    hi = np.searchsorted(t_s, rests.t_end_s, "right")
    keep = (hi - lo) >= 8
    if keep.sum() < 3:
        return None
    d2 = [np.mean(np.diff(y[a:b], axis=0) ** 2, axis=0) / 2 for a, b in zip(lo[keep], hi[keep], strict=True)]
    sigma2 = np.median(np.array(d2), axis=0)  # white noise and quantisation, robust to a bad rest
    if np.any(sigma2 <= 0):
        return None
    m = (hi - lo)[keep].astype(float)
    s2 = np.array([np.var(y[a:b], axis=0, ddof=1) for a, b in zip(lo[keep], hi[keep], strict=True)])
    chi2 = (m - 1)[:, None] * s2 / sigma2  # (k, 3)
    k = int(keep.sum())
    mid = np.repeat(0.5 * (rests.t_start_s + rests.t_end_s)[keep], 3)
    return RowSet(np.sqrt(chi2).ravel(), np.repeat(m - 1, 3), np.full(3 * k, "mag"), np.tile(np.arange(3), k),
                  np.full(3 * k, "static"), mid,
                  {"time s": mid, "temperature degC": np.repeat(rests.temperature[keep], 3)}, family="noise")

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

Inside the motions the heading is carried by the gyro: the calibrated field at every sample of a
motion is its field in the body at the motion's start (a nuisance per motion, fitted to the
motion's samples) turned by the attitude the calibrated gyro integrates to that sample. The
rows are whitened by the sample's noise (the rests' successive differences, through the
calibration) plus the attitude error the gyro's white noise leaves at that point, and each
counts one minus its leverage under the per-motion fit: a time offset between the triads, an
interference while moving, a soft-iron error the rests leave unseen show there.

Within-rest scatter is tested per rest and axis against that rest's own successive
differences (von Neumann's ratio): independent samples pass, whatever their noise level or
quantisation; an interference of ~1 Hz, slow wander or a vibrating support do not. The bias's
thermal drift the calibration models (``k``) is taken out first.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import least_squares

from ..models import TriadCalibration
from ..observations import Rests
from .attitude import Attitude
from .evaluate import Evaluation, white_noise
from .residual_map import RowSet, _gravity_cell

ROW_CHUNK = 65536  # motion samples whose (n, 3, 3) rotations and whiteners are formed at once (memory)


def rest_rows(rests: Rests, accel: TriadCalibration, mag: TriadCalibration
              ) -> tuple[RowSet, TriadCalibration] | None:
    """Magnitude and dip rows of every rest (axis -1: they belong to no single axis), with the
    magnetometer's calibration refitted to them (as the map judges the model, not the estimation
    error of a calibration fitted to fewer or differently weighted data), and that refit."""
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
    M, b, k_T, _ = unpack(fit.x)
    refit = dataclasses.replace(mag, M=M, b0=b, k=k_T if thermal else mag.k)
    return RowSet(r, w, np.full(2 * k, "mag"), np.full(2 * k, -1), np.full(2 * k, "static"), t, var), refit


MIN_MOTION_SAMPLES = 10  # a motion with fewer magnetometer samples tells little beyond its own nuisance


def motion_rows(ev: Evaluation, rests: Rests, t_s: np.ndarray, y: np.ndarray, mag: TriadCalibration,
                temperature: tuple[np.ndarray, np.ndarray] | None = None) -> RowSet | None:
    """The magnetometer's samples ``y`` (n, 3) raw at ``t_s`` (n,) s inside the fitted model's
    motions: each calibrated sample minus its motion's start-frame field turned by the gyro's
    attitude (``Attitude.rotation_at``), whitened, with the per-motion field fitted (3 dof each).
    ``mag``: the calibration refitted to the rests (``rest_rows``), as the map judges the model."""
    model, lin = ev.lin.model, ev.lin
    ms = model.motions
    if not len(ms.t) or not len(t_s):
        return None
    P = model.unpack(lin.x_g)
    omega, _ = model._rates(P, lin.x_l, derivatives=False)
    att = Attitude.integrate(model.quad, omega)
    # each sample's motion: inside [first, last] gyro sample of one (motions do not overlap)
    order = np.argsort(ms.origin)
    k = np.searchsorted(ms.origin[order], t_s, "right") - 1
    motion = np.where(k >= 0, order[np.maximum(k, 0)], -1)
    inside = (k >= 0) & (t_s <= ms.end[np.maximum(motion, 0)])
    for e in ev.events:  # a motion that carried the unit elsewhere may end in another field
        if e.kind == "translation":
            inside &= (t_s < e.window[0]) | (t_s > e.window[1])
    counts = np.bincount(motion[inside], minlength=ms.count)
    inside &= counts[np.maximum(motion, 0)] >= MIN_MOTION_SAMPLES
    if not inside.any():
        return None
    t, j = t_s[inside], motion[inside]
    T = np.interp(t, *temperature) if temperature is not None and len(temperature[0]) else None
    h = mag.apply(y[inside], T) @ ev.frame.T  # the calibration's frame -> the model's (gauge): Q v
    # noise: the sample's, through the calibration; the attitude error the gyro's white noise
    # leaves after tau s of a motion turns the field across itself: F^2 tau dt sigma_w^2
    Mg = ev.frame @ mag.M
    C0 = Mg @ white_noise(rests, {"mag": (t_s, y)}, "mag") @ Mg.T
    Sg = P["M_g"] @ model.noise.gyro_sample @ P["M_g"].T
    dt = float(np.median(np.diff(ms.t)[np.diff(ms.motion) == 0])) if len(ms.t) > 1 else 0.0
    tau = t - ms.origin[j]

    def whitened(c: slice) -> tuple[np.ndarray, np.ndarray]:
        """The rotations R (body at the sample -> body at the motion's start) and the whiteners
        L^-1 (C = L L') of samples ``c``: (n, 3, 3) each, formed by chunks (their temporaries)
        and kept from the fields' sums to the rows (144 bytes a sample)."""
        R = att.rotation_at(model.quad.points(t[c], j[c]))
        n = h[c] / np.maximum(np.linalg.norm(h[c], axis=1, keepdims=True), 1e-300)
        C = np.broadcast_to(C0, (len(n), 3, 3)) + \
            (np.einsum("ni,ni->n", h[c], h[c]) * tau[c] * dt * np.trace(Sg) / 3)[:, None, None] * \
            (np.eye(3) - n[:, :, None] * n[:, None, :])
        return R, np.linalg.inv(np.linalg.cholesky(C))

    # per motion: b = (sum R C^-1 R')^-1 sum R C^-1 h, the field in the body at its start
    A = np.zeros((ms.count, 3, 3))
    c = np.zeros((ms.count, 3))
    chunks = [slice(a, a + ROW_CHUNK) for a in range(0, len(t), ROW_CHUNK)]
    formed = [whitened(sl) for sl in chunks]
    for sl, (R, L_inv) in zip(chunks, formed, strict=True):
        RCi = R @ (np.swapaxes(L_inv, 1, 2) @ L_inv)
        np.add.at(A, j[sl], RCi @ np.swapaxes(R, 1, 2))
        np.add.at(c, j[sl], np.einsum("nij,nj->ni", RCi, h[sl]))
    used = np.unique(j)
    A_inv = np.zeros_like(A)
    A_inv[used] = np.linalg.inv(A[used])
    b = np.einsum("mij,mj->mi", A_inv, c)
    r, lev = np.empty((len(t), 3)), np.empty((len(t), 3))
    for sl, (R, L_inv) in zip(chunks, formed, strict=True):
        X = L_inv @ np.swapaxes(R, 1, 2)  # d (whitened row) / d b
        r[sl] = np.einsum("nij,nj->ni", L_inv, h[sl] - np.einsum("nji,nj->ni", R, b[j[sl]]))
        lev[sl] = np.einsum("nij,njk,nik->ni", X, A_inv[j[sl]], X)
    omega_t = np.linalg.norm(np.column_stack([np.interp(t, ms.t, omega[:, a]) for a in range(3)]), axis=1)
    var = {"|omega| rad/s": np.repeat(omega_t, 3), "time s": np.repeat(t, 3)}
    if T is not None:
        var["temperature degC"] = np.repeat(T, 3)
    m = len(t)
    return RowSet(r.ravel(), np.clip(1 - lev, 1e-3, 1).ravel(), np.full(3 * m, "mag"), np.tile(np.arange(3), m),
                  np.full(3 * m, "motion"), np.repeat(t, 3), var)


MIN_SCATTER_SAMPLES = 20  # below, von Neumann's ratio is too far from normal for its chi-square equivalent


def scatter_rows(rests: Rests, t_s: np.ndarray, y: np.ndarray, k: np.ndarray | None = None,
                 temperature: tuple[np.ndarray, np.ndarray] | None = None) -> RowSet | None:
    """Within-rest scatter of the raw magnetometer ``y`` (n, 3) at ``t_s`` (n,) s, one row per rest
    and axis: von Neumann's ratio of the rest's samples as its chi-square equivalent on ``m - 1``
    dof (``von_neumann_chi2``). ``k`` (3,) raw units per degC and ``temperature`` (t s, T degC):
    the calibration's thermal drift, removed before."""
    if not len(t_s) or not len(rests):
        return None
    if k is not None and temperature is not None and np.any(k):
        y = y - np.outer(np.interp(t_s, *temperature), k)
    lo = np.searchsorted(t_s, rests.t_start_s, "left")
    hi = np.searchsorted(t_s, rests.t_end_s, "right")
    keep = (hi - lo) >= MIN_SCATTER_SAMPLES
    if keep.sum() < 3:
        return None
    chi2, dof = zip(*(von_neumann_chi2(y[a:b]) for a, b in zip(lo[keep], hi[keep], strict=True)), strict=True)
    chi2, dof = np.array(chi2), np.array(dof, float)  # (k, 3), (k,)
    k = int(keep.sum())
    mid = np.repeat(0.5 * (rests.t_start_s + rests.t_end_s)[keep], 3)
    ok = np.isfinite(chi2).ravel()  # a rest whose quantised output never changes tells nothing
    return RowSet(np.sqrt(chi2).ravel()[ok], np.repeat(dof, 3)[ok], np.full(3 * k, "mag")[ok],
                  np.tile(np.arange(3), k)[ok], np.full(3 * k, "static")[ok], mid[ok],
                  {"time s": mid[ok], "temperature degC": np.repeat(rests.temperature[keep], 3)[ok]}, family="noise")


def von_neumann_chi2(x: np.ndarray) -> tuple[np.ndarray, int]:
    """(3,) chi-square equivalents on ``m - 1`` dof of the scatter of ``x`` (m, 3) about its mean
    beyond what its successive differences show.

    von Neumann's ratio ``Q = sum(diff(x)^2) / sum((x - mean)^2)`` of independent samples has
    mean 2 and variance ``4 (m - 2) / (m^2 - 1)`` exactly under normality (for any noise level;
    quantisation keeps the samples independent); its standard score ``z`` (positive when the
    scatter exceeds the differences) goes to the chi-square scale by Wilson-Hilferty:
    ``(m - 1) (1 - a + z sqrt(a))^3``, ``a = 2 / (9 (m - 1))``. NaN where ``x`` is constant."""
    m = len(x)
    e2 = np.sum((x - x.mean(axis=0)) ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.sum(np.diff(x, axis=0) ** 2, axis=0) / np.where(e2 > 0, e2, np.nan)
    z = (2 - q) / np.sqrt(4 * (m - 2) / (m * m - 1.0))
    a = 2 / (9 * (m - 1))
    return (m - 1) * np.clip(1 - a + z * np.sqrt(a), 0, None) ** 3, m - 1

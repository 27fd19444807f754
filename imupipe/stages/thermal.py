"""Thermal fit: bias-temperature coefficients from a warm-up at rest (method A, first step).

The warm-up is a window given in seconds, or else the longest rest of the
segmentation. Samples are averaged over ``average_s`` (the paper: 1 s) and
handed, per triad, to the configured ``thermal`` solver. The output
``calibration`` rows carry ``k`` (and, for the gyro, ``b0``) with ``M = I``:
downstream stages take ``k`` from them; they are not a calibration to export.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping
from typing import Literal

import numpy as np
import pyarrow as pa
from pydantic import Field, field_validator

from ..components import BoundSolver, Params, Stage
from ..errors import SolverError
from ..models import triads_to_table
from ..observations import Rests, ThermalObservations, TriadFit
from ._calib_common import concat_residuals, residual_table
from .segment import xyz


class ThermalParams(Params):
    """``average_s``: averaging interval (paper: 1 s); ``warmup_window_s``: [start, end]
    in s since the session start, or None for the longest rest; ``sensors``: the
    triads to fit (those wired and present); ``on_insufficient``: when the warm-up cannot
    identify k (too short or too little heating), raise (``error``) or warn and pass
    ``k = 0`` on (``zero``)."""

    average_s: float = Field(1.0, gt=0)
    warmup_window_s: tuple[float, float] | None = None
    sensors: tuple[Literal["accel", "gyro", "mag"], ...] = ("accel", "gyro", "mag")
    on_insufficient: Literal["error", "zero"] = "error"
    solver: str = "thermal_kalman"
    solver_params: dict = Field(default_factory=dict)

    @field_validator("warmup_window_s")
    @classmethod
    def _ordered(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not 0 <= v[0] < v[1]:
            raise ValueError(f"[start, end] = {list(v)}: need 0 <= start < end (s)")
        return v


def bin_average(t_s: np.ndarray, v: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Means over consecutive ``width``-second bins: times (m,), values (m, ...)."""
    b = np.floor((t_s - t_s[0]) / width).astype(np.int64)
    _, inv, cnt = np.unique(b, return_inverse=True, return_counts=True)
    tm = np.bincount(inv, weights=t_s) / cnt
    vm = np.column_stack([np.bincount(inv, weights=c) / cnt for c in np.atleast_2d(v.T)])
    return tm, vm


def average_sigma(v: np.ndarray) -> np.ndarray:
    """(3,) noise of one average, robust to the slow thermal trend: MAD of first differences."""
    d = np.diff(v, axis=0)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)


def _honest_cov(fit, z: np.ndarray, batches: int = 8):
    """The fit with its covariance inflated per axis by what its whitened residuals ``z`` (n, 3)
    show: their chi2/dof and, from ``batches`` batch means, their correlation (a bias walk or a
    lagging read-out over the warm-up makes neighbouring averages agree, and the white-noise
    covariance then understates the uncertainty of k several-fold)."""
    from ..allan import batch_variance_ratio  # SciPy's optimize: loaded when a stage runs

    factor = np.maximum(1.0, np.sum(z ** 2, axis=0) / max(len(z) - 2, 1))
    ratio = batch_variance_ratio(z, batches)
    if ratio is not None:
        factor = factor * np.maximum(1.0, np.nan_to_num(ratio, nan=1.0))
    d = np.sqrt(np.tile(factor, 2))  # b0 (3), k (3): each axis by its own factor
    return dataclasses.replace(fit, cov=np.asarray(fit.cov) * np.outer(d, d))


def warmup_window(inputs: Mapping[str, pa.Table], p: ThermalParams, t0: int) -> tuple[float, float]:
    if p.warmup_window_s is not None:
        return p.warmup_window_s
    if "rests" not in inputs:
        raise SolverError("fit_thermal: no warm-up window; give warmup_window_s = [start, end] "
                          "or wire the segmentation's rests (the longest rest is used)")
    rests = Rests.from_table(inputs["rests"])
    i = int(np.argmax(rests.t_end_s - rests.t_start_s))
    shift = (rests.t0_ns - t0) * 1e-9
    return rests.t_start_s[i] + shift, rests.t_end_s[i] + shift


def fit_thermal(inputs: Mapping[str, pa.Table], params: ThermalParams, solver: BoundSolver | None):
    tt = inputs["temperature"].column("t_ns").to_numpy()
    TT = inputs["temperature"].column("temperature").to_numpy()
    t0 = int(tt[0])
    for s in ("accel", "gyro", "mag"):
        if s in inputs:
            t0 = min(t0, int(inputs[s].column("t_ns")[0].as_py()))
    a, b = warmup_window(inputs, params, t0)
    triads, residuals = [], []
    for sensor in params.sensors:
        if sensor not in inputs:
            continue
        t, v = xyz(inputs[sensor])
        ts = (t - t0) * 1e-9
        sel = (ts >= a) & (ts <= b)
        if sel.sum() < 10:
            raise SolverError(f"fit_thermal: only {sel.sum()} {sensor} samples in the warm-up "
                              f"[{a:.1f}, {b:.1f}] s; check warmup_window_s")
        tm, vm = bin_average(ts[sel], v[sel], params.average_s)
        Tm = np.interp(tm, (tt - t0) * 1e-9, TT)
        obs = ThermalObservations(sensor, tm, Tm, vm, average_sigma(vm))
        try:
            fit = solver.solve(obs)
        except SolverError as exc:
            if params.on_insufficient == "error":
                raise
            warnings.warn(f"{exc}; continuing with k = 0", stacklevel=2)
            triads.append(TriadFit(np.eye(3), np.zeros(3), np.zeros((12, 12))).to_calibration(
                sensor, solver.solver.name, extra={"k_fitted": False, "reason": str(exc),
                                                   "role": "thermal coefficients only (M = I)"}))
            continue
        pred = fit.b0 + np.outer(Tm - obs.T_ref_C, fit.k)
        fit = _honest_cov(fit, (vm - pred) / obs.sigma)
        sd = np.sqrt(np.clip(np.diag(fit.cov), 0, None))
        keep_b0 = sensor == "gyro"  # accel/mag: b0 holds the projection of g or B (paper)
        details = {**dict(fit.details), "sigma_k": sd[3:].tolist(),
                   "sigma_b0": (sd[:3] if keep_b0 else np.zeros(3)).tolist(),
                   "covariance": np.asarray(fit.cov).tolist(), "covariance_order": "b0 (3), k (3)",
                   "warmup_window_s": [a, b], "k_fitted": True,
                   "role": "thermal coefficients only (M = I)"}
        triads.append(TriadFit(np.eye(3), fit.b0 if keep_b0 else np.zeros(3), np.zeros((12, 12)))
                      .to_calibration(sensor, solver.solver.name, k=fit.k, sigma_k=sd[3:],
                                      extra=details))
        residuals.append(residual_table("fit_thermal", sensor, "average", tm, Tm, vm, pred,
                                        np.tile(obs.sigma, (len(tm), 1))))
    if not residuals:
        residuals.append(residual_table("fit_thermal", "gyro", "average", np.zeros(0), np.zeros(0),
                                        np.zeros((0, 3)), np.zeros((0, 3)), None))
    if not triads:
        raise SolverError("fit_thermal: no triad wired; connect accel, gyro and/or mag samples")
    return {"calibration": triads_to_table(triads), "residuals": concat_residuals(residuals)}


STAGE = Stage(
    name="fit_thermal", version="2", func=fit_thermal,
    inputs={"temperature": "temperature", "accel": "accel", "gyro": "gyro", "mag": "mag",
            "rests": "rests"},
    outputs={"calibration": "calibration", "residuals": "residuals"}, params=ThermalParams,
    optional_inputs=frozenset({"accel", "gyro", "mag", "rests"}), solver_kind="thermal",
    description="bias temperature coefficients k from a warm-up at rest",
)
COMPONENTS = [STAGE]

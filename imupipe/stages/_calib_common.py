"""Helpers the method A calibrate stages share: thermal k lookup, residual tables, noise."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa

from .. import schemas
from ..errors import SolverError
from ..models import T_REF_C, TriadCalibration, triads_from_table
from ..observations import Rests, TriadFit


def triad_from(inputs: Mapping[str, pa.Table], port: str, sensor: str) -> TriadCalibration | None:
    """The ``sensor`` row of the calibration table on ``port``, or None if the port is unwired."""
    if port not in inputs:
        return None
    for t in triads_from_table(inputs[port]):
        if t.sensor == sensor:
            return t
    return None


def need_triad(inputs: Mapping[str, pa.Table], port: str, sensor: str, stage: str) -> TriadCalibration:
    triad = triad_from(inputs, port, sensor)
    if triad is None:
        raise SolverError(f"{stage}: the table on input {port!r} holds no {sensor} calibration; "
                          f"wire the {sensor} calibration stage's output there")
    return triad


def thermal_k(inputs: Mapping[str, pa.Table], sensor: str) -> tuple[np.ndarray, np.ndarray]:
    """(k (3,), sigma_k (3,)) from the optional ``thermal`` input; zeros when unwired."""
    t = triad_from(inputs, "thermal", sensor)
    if t is None:
        return np.zeros(3), np.zeros(3)
    return t.k, np.asarray(t.details.get("sigma_k", np.zeros(3)), dtype=float)


def dT(T: np.ndarray) -> np.ndarray:
    """Temperature minus T_REF_C (25 degC); zero where the temperature is unknown (NaN)."""
    return np.nan_to_num(np.asarray(T, dtype=float) - T_REF_C)


def noise_details(rests: Rests, sensor: str) -> dict:
    """White sigma of one sample per axis and the rest-to-rest scatter of the means.

    ``rest_to_rest_sigma`` is the spread of successive rest means beyond white
    noise; meaningful for the gyro (bias drift), attitude-driven for accel and mag.
    """
    white = rests.white_sigma(sensor)
    out = {"white_sigma": white.tolist(), "white_sigma_unit": "per sample"}
    if sensor == "gyro" and len(rests) > 2:
        d = np.diff(rests.mean[sensor], axis=0)
        white_part = white**2 * (1 / rests.counts[sensor][1:] + 1 / rests.counts[sensor][:-1]).mean()
        out["rest_to_rest_bias_sigma"] = np.sqrt(np.clip(np.var(d, axis=0) / 2 - white_part / 2,
                                                         0, None)).tolist()
    return out


def residual_table(stage: str, sensor: str, kind: str, t_s: np.ndarray, T: np.ndarray,
                   measured: np.ndarray, predicted: np.ndarray, sigma: np.ndarray | None,
                   before: np.ndarray | None = None, after: np.ndarray | None = None) -> pa.Table:
    """A ``residuals`` table; ``sigma`` (n, 3) 1-sigma of each measurement or None."""
    n = len(measured)
    resid = measured - predicted
    norm = resid / sigma if sigma is not None else np.full((n, 3), np.nan)
    nan = np.full(n, np.nan)
    l3 = pa.list_(pa.float64(), 3)
    table = pa.table({
        "stage": [stage] * n, "sensor": [sensor] * n, "kind": [kind] * n,
        "index": np.arange(n, dtype=np.int64), "t_s": np.asarray(t_s, float),
        "temperature": np.asarray(T, float),
        "measured": pa.array(list(measured), type=l3), "predicted": pa.array(list(predicted), type=l3),
        "residual": pa.array(list(resid), type=l3), "normalised": pa.array(list(norm), type=l3),
        "norm_error_before": nan if before is None else before,
        "norm_error_after": nan if after is None else after,
    })
    return schemas.stamp(table, "residuals")


def concat_residuals(tables: list[pa.Table]) -> pa.Table:
    first = tables[0].schema  # cast only a table of other types (a cast imports pyarrow.compute)
    return schemas.stamp(pa.concat_tables([t if t.schema.equals(first) else t.cast(first) for t in tables]),
                         "residuals")


def rest_at_time(rests: Rests, t_s: float) -> int:
    """Index of the rest containing ``t_s`` (s since the session start), else the nearest."""
    inside = np.flatnonzero((rests.t_start_s <= t_s) & (rests.t_end_s >= t_s))
    if len(inside):
        return int(inside[0])
    mid = 0.5 * (rests.t_start_s + rests.t_end_s)
    return int(np.argmin(np.abs(mid - t_s)))


def model_T(T: np.ndarray) -> np.ndarray:
    """Temperatures for ``apply``/``predict``: unknown (NaN) is taken as T_REF_C (no thermal term)."""
    return np.where(np.isfinite(T), T, T_REF_C)


def add_thermal_variance(fit: TriadFit, T: np.ndarray, sigma_k: np.ndarray) -> TriadFit:
    """``fit`` with the b0 variance the k uncertainty adds: b0 sits ``mean(T) - 25`` away
    from the rests' temperatures, so an error in k moves it by that much."""
    cov = np.array(fit.cov, dtype=float)
    cov[9:, 9:] += np.diag((np.nanmean(dT(T)) * np.asarray(sigma_k)) ** 2) if len(T) else 0.0
    return TriadFit(fit.M, fit.b0, cov, fit.details)

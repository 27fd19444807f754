"""Magnetometer alone from a free tumble: hard and soft iron, no rests, no accelerometer.

MATLAB ``magcal``'s job. The magnetometer stream is cut into short windows
(``window_s``); each window's mean is one point of the field ellipsoid (the
sensor may move: the field is the same in every orientation, only its direction
in the sensor changes). The points go to a ``mag`` solver that needs no
gravity (``ellipsoid_magcal``). The white noise of one sample comes from the
first differences of the stream (robust, nearly blind to the slow motion), the
covariance of a window's mean from it and the window's sample count.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from ..components import BoundSolver, FieldStrength, Params, Stage
from ..errors import SolverError
from ..models import triads_to_table
from ..observations import EllipsoidObservations
from ..solvers.ellipsoid_cholesky import coverage
from ._calib_common import residual_table
from .segment import xyz


class MagFreeParams(Params):
    """``window_s``: length of the windows averaged into one point; ``max_points``: at most
    this many windows, evenly spaced in time, go to the fit; ``field_T``: local field
    magnitude (None: the ellipsoid's mean radius, i.e. the sensor's own scale on average);
    ``min_coverage``: how evenly the tumble must cover the sphere (1 = uniform), about the
    data's mean before the fit and about the fitted centre after it; ``max_anisotropy``: the
    largest ratio of M's singular values believed (a soft iron stretching the field by more is
    taken for a fit the data do not determine)."""

    window_s: float = Field(0.1, gt=0)
    max_points: int = Field(2000, ge=12)
    field_T: FieldStrength | None = None
    min_coverage: float = Field(0.35, ge=0, le=1)
    max_anisotropy: float = Field(2.0, gt=1)
    solver: str = "ellipsoid_magcal"
    solver_params: dict = Field(default_factory=dict)


def windows(t_ns: np.ndarray, v: np.ndarray, window_s: float):
    """(t_mid_s (n,), mean (n, 3), count (n,)) of consecutive windows of ``window_s``."""
    k = np.floor((t_ns - t_ns[0]) * 1e-9 / window_s).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, np.diff(k) != 0])
    count = np.diff(np.r_[starts, len(k)])
    mean = np.add.reduceat(v, starts, axis=0) / count[:, None]
    t_mid = np.add.reduceat((t_ns - t_ns[0]) * 1e-9, starts) / count
    return t_mid, mean, count


def white_sigma(v: np.ndarray) -> np.ndarray:
    """(3,) white noise of one sample from first differences (MAD, robust to motion)."""
    d = np.diff(v, axis=0)
    if len(d) < 2:
        return np.full(3, np.nan)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)


def calibrate_mag_free(inputs: Mapping[str, pa.Table], params: MagFreeParams,
                       solver: BoundSolver | None):
    t_ns, m = xyz(inputs["mag"])
    keep = np.all(np.isfinite(m), axis=1)
    t_ns, m = t_ns[keep], m[keep]
    if len(m) < 12:
        raise SolverError(f"calibrate_mag_free: only {len(m)} magnetometer samples; a free tumble "
                          "through every orientation needs hundreds")
    t_mid, y, count = windows(t_ns, m, params.window_s)
    if len(y) > params.max_points:
        pick = np.unique(np.round(np.linspace(0, len(y) - 1, params.max_points)).astype(int))
        t_mid, y, count = t_mid[pick], y[pick], count[pick]
    cov_q = coverage(y - y.mean(axis=0))
    if cov_q < params.min_coverage:
        raise SolverError(
            f"calibrate_mag_free: the tumble covers the sphere poorly (coverage {cov_q:.2f}, need "
            f">= {params.min_coverage}); turn the sensor through every orientation (each axis "
            "up and down, figure-eights), or lower min_coverage knowing the fit is weaker"
        )
    sigma = white_sigma(m)
    cov = np.einsum("n,ij->nij", 1.0 / count, np.diag(np.nan_to_num(sigma) ** 2))
    T = np.full(len(y), np.nan)

    def run(magnitude: float):
        return solver.solve(EllipsoidObservations("mag", y, cov, T, magnitude))

    if params.field_T is not None:
        magnitude, field_source = params.field_T, "field_T parameter"
    else:  # the unit-field fit's mean radius: M keeps the sensor's nominal scale (det M = 1)
        magnitude = abs(np.linalg.det(np.asarray(run(1.0).M))) ** (-1 / 3)
        field_source = "ellipsoid mean radius (set field_T for absolute scale)"
    fit = run(magnitude)
    M, b = np.asarray(fit.M), np.asarray(fit.b0)
    cov_fit, sv = coverage(y - b), np.linalg.svd(M, compute_uv=False)
    if cov_fit < params.min_coverage or sv[0] / sv[-1] > params.max_anisotropy:
        raise SolverError(
            f"calibrate_mag_free: the data do not determine the ellipsoid: about the fitted centre "
            f"the points cover {cov_fit:.2f} of the sphere (need >= {params.min_coverage}) and "
            f"M stretches {sv[0] / sv[-1]:.2f}:1 (believed up to {params.max_anisotropy}); the "
            "recording does not turn the sensor through every orientation (a flight or a drive "
            "mostly yaws); record a tumble with each axis up and down")
    cal = fit.to_calibration("mag", solver.solver.name, extra={
        "noise": {"white_sigma": sigma.tolist(), "white_sigma_unit": "per sample"},
        "field_T": magnitude, "field_source": field_source, "n_windows": len(y),
        "window_s": params.window_s, "source": "free tumble (no rests)",
    })
    x = cal.apply(y)
    nx = np.linalg.norm(x, axis=1)
    predicted = cal.predict(x / nx[:, None] * magnitude)
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    res = residual_table("calibrate_mag_free", "mag", "rest", t_mid, T, y, predicted,
                         np.where(sig > 0, sig, np.nan),
                         np.linalg.norm(y, axis=1) / magnitude - 1, nx / magnitude - 1)
    return {"calibration": triads_to_table([cal]), "residuals": res}


STAGE = Stage(
    name="calibrate_mag_free", version="1", func=calibrate_mag_free,
    inputs={"mag": "mag"}, outputs={"calibration": "calibration", "residuals": "residuals"},
    params=MagFreeParams, solver_kind="mag",
    description="magnetometer hard and soft iron from a free tumble (no rests, no accelerometer)",
)
COMPONENTS = [STAGE]

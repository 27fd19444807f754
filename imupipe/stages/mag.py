"""Magnetometer calibration from the rests, tied to the corrected accelerometer (eqs. 21-25).

The dip angle comes from params (``dip_deg``), else from turntable circles
(``circle_windows_s``: full turns of the rig base on a level table, paper
Fig. 4c), else the ``mag`` solver estimates it from the rests. The correction
returns tesla: the local field magnitude is ``field_T`` when given (from a
field model such as WMM/IGRF), else the fitted ellipsoid's mean radius, i.e.
the sensor's own nominal scale on average (``det M = 1``); ``details.field_source``
says which.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field, field_validator

from ..components import BoundSolver, FieldStrength, Params, Stage
from ..models import triads_to_table
from ..observations import EllipsoidObservations, Rests
from ..solvers.mag_dip import circle_dip
from ._calib_common import (
    add_thermal_variance,
    dT,
    model_T,
    need_triad,
    noise_details,
    residual_table,
    thermal_k,
)
from .segment import xyz


class MagParams(Params):
    """``field_T``: local field magnitude (None: the ellipsoid's mean radius); ``dip_deg``: local dip,
    positive downward (None: measured); ``circle_windows_s``: [[start, end], ...] s
    since the session start, each one full turn of the rig base."""

    field_T: FieldStrength | None = None
    dip_deg: float | None = Field(None, ge=-90, le=90)
    circle_windows_s: tuple[tuple[float, float], ...] = ()
    min_rest_s: float = Field(0.0, ge=0)
    solver: str = "ellipsoid_dip"
    solver_params: dict = Field(default_factory=dict)

    @field_validator("circle_windows_s")
    @classmethod
    def _ordered(cls, v: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
        for a, b in v:
            if not a < b:
                raise ValueError(f"window [{a}, {b}]: need start < end (s)")
        return v


def calibrate_mag(inputs: Mapping[str, pa.Table], params: MagParams, solver: BoundSolver | None):
    rests = Rests.from_table(inputs["rests"])
    rests = rests.subset((rests.t_end_s - rests.t_start_s) >= params.min_rest_s)
    y_raw = rests.need("mag")
    acc = need_triad(inputs, "accel", "accel", "calibrate_mag")
    k, sigma_k = thermal_k(inputs, "mag")
    y = y_raw - np.outer(dT(rests.temperature), k)
    gravity = acc.apply(rests.need("accel"), model_T(rests.temperature))
    gravity /= np.linalg.norm(gravity, axis=1, keepdims=True)
    dip = np.radians(params.dip_deg) if params.dip_deg is not None else None

    def run(dip_rad, magnitude):
        return solver.solve(EllipsoidObservations(
            "mag", y, rests.cov_of_mean("mag"), rests.temperature, magnitude,
            gravity=gravity, dip_rad=dip_rad))

    if params.field_T is not None:
        magnitude, field_source = params.field_T, "field_T parameter"
    else:  # the unit-field fit's mean radius: M then keeps the sensor's nominal scale (det M = 1)
        magnitude = abs(np.linalg.det(np.asarray(run(dip, 1.0).M))) ** (-1 / 3)
        field_source = "ellipsoid mean radius (set field_T for absolute scale)"
    fit = run(dip, magnitude)
    dip_info = {"dip_source": fit.details.get("dip_source")}
    if dip is None and params.circle_windows_s:
        t, m = xyz(inputs["mag"])
        ts = (t - rests.t0_ns) * 1e-9
        M, b = np.asarray(fit.M), np.asarray(fit.b0)
        circles = []
        for a, bnd in params.circle_windows_s:
            x = (m[(ts >= a) & (ts <= bnd)] - b) @ M.T
            circles.append(x / np.linalg.norm(x, axis=1, keepdims=True))
        dip, radii = circle_dip(circles)
        fit = run(dip, magnitude)
        dip_info = {"dip_source": "turntable circles", "circle_radii": radii}
    fit = add_thermal_variance(fit, rests.temperature, sigma_k)
    cal = fit.to_calibration("mag", solver.solver.name, k=k, sigma_k=sigma_k, extra={
        **dip_info, "noise": noise_details(rests, "mag"),
        "field_T": magnitude, "field_source": field_source,
    })
    x = cal.apply(y_raw, model_T(rests.temperature))
    nx = np.linalg.norm(x, axis=1)
    predicted = cal.predict(x / nx[:, None] * magnitude, model_T(rests.temperature))
    sigma = np.sqrt(np.diagonal(rests.cov_of_mean("mag"), axis1=1, axis2=2))
    raw_norm = np.linalg.norm(y_raw, axis=1)
    before = raw_norm / magnitude - 1
    res = residual_table("calibrate_mag", "mag", "rest", 0.5 * (rests.t_start_s + rests.t_end_s),
                         rests.temperature, y_raw, predicted, sigma, before, nx / magnitude - 1)
    return {"calibration": triads_to_table([cal]), "residuals": res}


STAGE = Stage(
    name="calibrate_mag", version="2", func=calibrate_mag,
    inputs={"rests": "rests", "accel": "calibration", "mag": "mag", "thermal": "calibration"},
    outputs={"calibration": "calibration", "residuals": "residuals"}, params=MagParams,
    optional_inputs=frozenset({"thermal"}), solver_kind="mag",
    description="magnetometer M, b0 from rests, rotation and scale through the dip angle",
)
COMPONENTS = [STAGE]

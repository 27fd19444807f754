"""Accelerometer calibration from the rests (method A: eqs. 7-20, or any ``accel`` solver).

Observations: the rest means with the thermal bias ``k (T - 25)`` removed when
the thermal stage is wired; the reference rests (instrument Y up / X up) come
from params, by index or by time, or are detected as the rests closest to the
sensor's +Y / +X axes. Residuals per rest: measured mean vs the model's
prediction for gravity along the corrected direction, and the paper's Fig. 4b
|g| errors before and after.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from ..components import BoundSolver, Params, Stage
from ..models import triads_to_table
from ..observations import EllipsoidObservations, Rests
from ._calib_common import (
    add_thermal_variance,
    dT,
    model_T,
    noise_details,
    residual_table,
    rest_at_time,
    thermal_k,
)

G_STANDARD = 9.80665


class AccelParams(Params):
    """``g_m_s2``: local gravity; ``y_up_rest``/``x_up_rest``: reference rests by index,
    or ``y_up_time_s``/``x_up_time_s`` by a time inside them (s since the session start);
    ``detect_reference``: otherwise take the longest rests whose raw direction is within
    ``detect_tol_deg`` of the sensor's +Y / +X axes; ``min_rest_s``: shorter rests are
    left out of the fit."""

    g_m_s2: float = G_STANDARD
    y_up_rest: int | None = None
    x_up_rest: int | None = None
    y_up_time_s: float | None = None
    x_up_time_s: float | None = None
    detect_reference: bool = False
    detect_tol_deg: float = 3.0
    min_rest_s: float = 0.0
    solver: str = "ellipsoid_cholesky"
    solver_params: dict = Field(default_factory=dict)


def reference_rests(rests: Rests, p: AccelParams) -> tuple[int | None, int | None, str]:
    """(y_up, x_up, how) indices into ``rests``."""
    y_up, x_up = p.y_up_rest, p.x_up_rest
    if y_up is None and p.y_up_time_s is not None:
        y_up = rest_at_time(rests, p.y_up_time_s)
    if x_up is None and p.x_up_time_s is not None:
        x_up = rest_at_time(rests, p.x_up_time_s)
    if y_up is not None or x_up is not None:
        return y_up, x_up, "config"
    if p.detect_reference:
        # reference rests are held level and longer than the others: among the rests whose raw
        # direction is within the tolerance of the axis, take the longest
        u = rests.mean["accel"] / np.linalg.norm(rests.mean["accel"], axis=1, keepdims=True)
        length = rests.t_end_s - rests.t_start_s
        found = []
        for axis in (1, 0):
            near = np.flatnonzero(np.degrees(np.arccos(np.clip(u[:, axis], -1, 1))) <= p.detect_tol_deg)
            found.append(int(near[np.argmax(length[near])]) if len(near) else None)
        return found[0], found[1] if found[0] is not None else None, "detected"
    return None, None, "none"


def calibrate_accel(inputs: Mapping[str, pa.Table], params: AccelParams, solver: BoundSolver | None):
    rests = Rests.from_table(inputs["rests"])
    rests = rests.subset((rests.t_end_s - rests.t_start_s) >= params.min_rest_s)
    y_raw = rests.need("accel")
    k, sigma_k = thermal_k(inputs, "accel")
    y = y_raw - np.outer(dT(rests.temperature), k)
    y_up, x_up, how = reference_rests(rests, params)
    obs = EllipsoidObservations("accel", y, rests.cov_of_mean("accel"), rests.temperature,
                                params.g_m_s2, y_up, x_up)
    fit = solver.solve(obs)
    fit = add_thermal_variance(fit, rests.temperature, sigma_k)
    cal = fit.to_calibration("accel", solver.solver.name, k=k, sigma_k=sigma_k, extra={
        "reference_rests": {"y_up": y_up, "x_up": x_up, "how": how},
        "noise": noise_details(rests, "accel"), "g_m_s2": params.g_m_s2,
    })
    x = cal.apply(y_raw, model_T(rests.temperature))
    nx = np.linalg.norm(x, axis=1)
    predicted = cal.predict(x / nx[:, None] * params.g_m_s2, model_T(rests.temperature))
    sigma = np.sqrt(np.diagonal(rests.cov_of_mean("accel"), axis1=1, axis2=2))
    before = np.linalg.norm(y_raw, axis=1) / params.g_m_s2 - 1
    after = nx / params.g_m_s2 - 1
    res = residual_table("calibrate_accel", "accel", "rest", 0.5 * (rests.t_start_s + rests.t_end_s),
                         rests.temperature, y_raw, predicted, sigma, before, after)
    return {"calibration": triads_to_table([cal]), "residuals": res}


STAGE = Stage(
    name="calibrate_accel", version="1", func=calibrate_accel,
    inputs={"rests": "rests", "thermal": "calibration"},
    outputs={"calibration": "calibration", "residuals": "residuals"}, params=AccelParams,
    optional_inputs=frozenset({"thermal"}), solver_kind="accel",
    description="accelerometer M, b0 from rests on the gravity ellipsoid",
)
COMPONENTS = [STAGE]

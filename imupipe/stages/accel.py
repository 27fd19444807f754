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
from pydantic import Field, model_validator

from ..components import BoundSolver, LocalGravity, Params, Stage
from ..errors import ConfigError
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
    """``g_m_s2``: local gravity; ``y_up_rest``/``x_up_rest``: reference rests by index
    into the segmentation's rests table (before ``min_rest_s``), or ``y_up_time_s``/
    ``x_up_time_s`` by a time inside them (s since the session start); X up needs Y up
    (eq. 19 turns about the Y-up axis); ``detect_reference``: otherwise take the longest
    rests whose raw direction is within ``detect_tol_deg`` of the sensor's +Y / +X axes;
    ``min_rest_s``: shorter rests are left out of the fit (reference rests stay in)."""

    g_m_s2: LocalGravity = G_STANDARD
    y_up_rest: int | None = Field(None, ge=0)
    x_up_rest: int | None = Field(None, ge=0)
    y_up_time_s: float | None = None
    x_up_time_s: float | None = None
    detect_reference: bool = False
    detect_tol_deg: float = Field(3.0, gt=0, le=90)
    min_rest_s: float = Field(0.0, ge=0)
    solver: str = "ellipsoid_cholesky"
    solver_params: dict = Field(default_factory=dict)

    @model_validator(mode="after")
    def _x_needs_y(self) -> AccelParams:
        if (self.x_up_rest is not None or self.x_up_time_s is not None) and \
                self.y_up_rest is None and self.y_up_time_s is None:
            raise ValueError("x_up_rest / x_up_time_s given without y_up_rest / y_up_time_s: the "
                             "X-up rest only fixes the turn about the Y-up axis (eq. 19); give "
                             "the Y-up rest too, or drop the X-up one")
        return self


def reference_rests(rests: Rests, p: AccelParams, usable: np.ndarray) -> tuple[int | None, int | None, str]:
    """(y_up, x_up, how) indices into ``rests`` (all of the segmentation's); detection
    looks only at the ``usable`` (n,) bool rests."""
    n = len(rests)
    for key in ("y_up_rest", "x_up_rest"):
        i = getattr(p, key)
        if i is not None and i >= n:
            raise ConfigError(f"calibrate_accel: {key} = {i} but the segmentation found {n} rests "
                              f"(valid indices 0..{n - 1}); check the rests table or use "
                              f"{key.replace('_rest', '_time_s')}")
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
            near = np.flatnonzero(usable & (np.degrees(np.arccos(np.clip(u[:, axis], -1, 1)))
                                            <= p.detect_tol_deg))
            found.append(int(near[np.argmax(length[near])]) if len(near) else None)
        return found[0], found[1] if found[0] is not None else None, "detected"
    return None, None, "none"


def calibrate_accel(inputs: Mapping[str, pa.Table], params: AccelParams, solver: BoundSolver | None):
    all_rests = Rests.from_table(inputs["rests"])
    all_rests.need("accel")
    keep = (all_rests.t_end_s - all_rests.t_start_s) >= params.min_rest_s
    y_up_all, x_up_all, how = reference_rests(all_rests, params, keep)
    refs = [i for i in (y_up_all, x_up_all) if i is not None]
    keep[refs] = True  # chosen reference rests stay in whatever their length
    rests = all_rests.subset(keep)
    position = np.cumsum(keep) - 1  # index among the kept rests
    y_up, x_up = (None if i is None else int(position[i]) for i in (y_up_all, x_up_all))
    y_raw = rests.need("accel")
    k, sigma_k = thermal_k(inputs, "accel")
    y = y_raw - np.outer(dT(rests.temperature), k)
    obs = EllipsoidObservations("accel", y, rests.cov_of_mean("accel"), rests.temperature,
                                params.g_m_s2, y_up, x_up)
    fit = solver.solve(obs)
    fit = add_thermal_variance(fit, rests.temperature, sigma_k)
    cal = fit.to_calibration("accel", solver.solver.name, k=k, sigma_k=sigma_k, extra={
        "reference_rests": {"y_up": y_up_all, "x_up": x_up_all, "how": how,
                            "index_into": "the segmentation's rests table"},
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
    name="calibrate_accel", version="2", func=calibrate_accel,
    inputs={"rests": "rests", "thermal": "calibration"},
    outputs={"calibration": "calibration", "residuals": "residuals"}, params=AccelParams,
    optional_inputs=frozenset({"thermal"}), solver_kind="accel",
    description="accelerometer M, b0 from rests on the gravity ellipsoid",
)
COMPONENTS = [STAGE]

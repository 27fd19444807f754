"""Non-linear bias temperature dependence: the bias gains ``k2_per_C2_i (T_die - 25)^2``
(units of the triad per degC^2). ``sensor`` picks the triad (accel, gyro or mag)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase, Vec3


class QuadraticParams(Params):
    k2_per_C2: Vec3 = Field(description="3, triad units per degC^2")
    sensor: Literal["accel", "gyro", "mag"] = Field("gyro", description="accel | gyro | mag")


class BiasTemperatureNonlinear(EffectBase):
    identifier = "bias_temperature_nonlinear"
    sensors = ("accel", "gyro", "mag")
    stage = "bias"
    params = QuadraticParams
    linear = ("k2_per_C2",)
    physics = "the bias has a term quadratic in temperature, beyond the linear coefficient k."

    def _apply(self, streams, ctx, p, rng) -> None:
        dT = streams["T_die"] - 25.0
        streams[p.sensor] = streams[p.sensor] + np.outer(dT**2, p.k2_per_C2)

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 3): d y / d k2_per_C2 given the temperature ``T`` (n,) degC."""
        dT = np.asarray(inputs["T"], float) - 25.0
        return np.einsum("n,ij->nij", dT**2, np.eye(3))


COMPONENTS = [BiasTemperatureNonlinear()]

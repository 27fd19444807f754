"""Accelerometer-gyro time offset: accelerometer samples describe the motion ``dt_s`` seconds before
their time stamp (positive: accel late). Exact in the simulator (the motion is evaluated at
t - dt_s); nothing changes at rest."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase


class TimeOffsetParams(Params):
    dt_s: float = Field(description="s, positive: accelerometer late")


class AccelGyroTimeOffset(EffectBase):
    identifier = "accel_gyro_time_offset"
    sensors = ("accel",)
    stage = "timing"
    params = TimeOffsetParams
    linear = ("dt_s",)
    physics = "the accelerometer's stamps are late relative to the gyro's, so rotating gravity lags."

    def _apply(self, streams, ctx, p, rng) -> None:
        streams["t_accel"] = streams["t_accel"] - p.dt_s

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 1): d f / d dt_s to first order, ``-df/dt`` given ``f_dot`` (n, 3), m/s^3."""
        return -np.asarray(inputs["f_dot"], float)[:, :, None]


COMPONENTS = [AccelGyroTimeOffset()]

"""Gyro saturation: the output clips at +-``limit_rad_s`` during fast rotations."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase


class SaturationParams(Params):
    limit_rad_s: float = Field(gt=0, description="rad/s")


class GyroSaturation(EffectBase):
    identifier = "gyro_saturation"
    sensors = ("gyro",)
    stage = "output"
    params = SaturationParams
    physics = "the gyro's range is exceeded and its output clips, losing rotation angle."

    def _apply(self, streams, ctx, p, rng) -> None:
        streams["gyro"] = np.clip(streams["gyro"], -p.limit_rad_s, p.limit_rad_s)


COMPONENTS = [GyroSaturation()]

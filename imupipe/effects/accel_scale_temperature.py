"""Accelerometer scale factor varies with temperature: axis i scale is 1 + s_i (T_die - 25), s in ppm/degC."""

from __future__ import annotations

from pydantic import Field

from ..components import Params
from ._base import ScaleTemperature, Vec3


class ScaleTemperatureParams(Params):
    ppm_per_C: Vec3 = Field(description="3, ppm per degC")


class AccelScaleTemperature(ScaleTemperature):
    identifier = "accel_scale_temperature"
    sensors = ("accel",)
    params = ScaleTemperatureParams


COMPONENTS = [AccelScaleTemperature()]

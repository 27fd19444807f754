"""Gyro scale factor varies with temperature: axis i scale is 1 + s_i (T_die - 25), s in ppm/degC."""

from __future__ import annotations

from ._base import ScaleTemperature
from .accel_scale_temperature import ScaleTemperatureParams


class GyroScaleTemperature(ScaleTemperature):
    identifier = "gyro_scale_temperature"
    sensors = ("gyro",)
    params = ScaleTemperatureParams


COMPONENTS = [GyroScaleTemperature()]

"""Gyro g-sensitivity: the gyro output gains ``G f`` (G in rad/s per m/s^2, f the true specific
force in the instrument frame). Invisible at a single orientation (absorbed by b0); at many static
orientations the static gyro means follow gravity in body axes."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase, Mat3


class GSensitivityParams(Params):
    G: Mat3 = Field(description="3x3, rad/s per m/s^2")


class GyroGSensitivity(EffectBase):
    identifier = "gyro_g_sensitivity"
    sensors = ("gyro",)
    stage = "bias"
    params = GSensitivityParams
    linear = ("G",)
    physics = "the gyro output gains G f, f the specific force (proof-mass deflection under acceleration)."

    def _apply(self, streams, ctx, p, rng) -> None:
        streams["gyro"] = streams["gyro"] + streams["f_body"] @ np.asarray(p.G, float).T

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 9): d y_gyro / d G (row-major) given the specific force ``f`` (n, 3), m/s^2."""
        f = np.asarray(inputs["f"], float)
        out = np.zeros((len(f), 3, 9))
        for i in range(3):
            out[:, i, 3 * i:3 * i + 3] = f
        return out


COMPONENTS = [GyroGSensitivity()]

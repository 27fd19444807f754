"""Accelerometer non-linearity: each sensor axis gains k2_i f_i^2 (k2 per m/s^2), f_i the specific
force that axis senses (``(S x)_i``). Half absorbed by scale and bias in a static calibration."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase, Vec3


class NonlinearityParams(Params):
    k2: Vec3 = Field(description="3, per m/s^2")


class AccelNonlinearity(EffectBase):
    identifier = "accel_nonlinearity"
    sensors = ("accel",)
    stage = "sensed"
    params = NonlinearityParams
    linear = ("k2",)
    physics = "each axis gains a term quadratic in the specific force it senses (k2_i f_i^2)."

    def _apply(self, streams, ctx, p, rng) -> None:
        u = streams["accel"]
        streams["accel"] = u + np.asarray(p.k2) * u**2

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 3): d y / d k2 given the sensed specific force ``x`` (n, 3), m/s^2."""
        x = np.asarray(inputs["x"], float)
        return np.einsum("ni,ij->nij", x**2, np.eye(3))


COMPONENTS = [AccelNonlinearity()]

"""Gyro scale-factor asymmetry: axis i scale is (1 + eps_i) for positive and (1 - eps_i) for
negative rate (of that sensor axis). Absorbed when every turn is undone by its reverse."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase, Vec3


class AsymmetryParams(Params):
    eps: Vec3 = Field(description="3, dimensionless")


class GyroScaleAsymmetry(EffectBase):
    identifier = "gyro_scale_asymmetry"
    sensors = ("gyro",)
    stage = "sensed"
    params = AsymmetryParams
    linear = ("eps",)
    physics = "the gyro's scale factor differs between positive and negative rates."

    def _apply(self, streams, ctx, p, rng) -> None:
        u = streams["gyro"]
        streams["gyro"] = u * (1.0 + np.asarray(p.eps) * np.sign(u))

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 3): d y / d eps given the sensed rate ``x`` (n, 3), rad/s: |x_i| on axis i."""
        x = np.asarray(inputs["x"], float)
        return np.einsum("ni,ij->nij", np.abs(x), np.eye(3))


COMPONENTS = [GyroScaleAsymmetry()]

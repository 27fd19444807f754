"""Lever arm: the accelerometer sits at ``r_m`` (body axes, m) from the centre of rotation and gains
alpha x r + omega x (omega x r). Invisible at rest."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ..rotations import skew
from ._base import EffectBase, Vec3


class LeverArmParams(Params):
    r_m: Vec3 = Field(description="3, m, body axes")


class LeverArm(EffectBase):
    identifier = "lever_arm"
    sensors = ("accel",)
    stage = "input"
    params = LeverArmParams
    linear = ("r_m",)
    physics = "the accelerometer is off the centre of rotation and feels tangential and centripetal acceleration."

    def _apply(self, streams, ctx, p, rng) -> None:
        r = np.asarray(p.r_m)
        w, a = streams["accel_omega"], streams["accel_alpha"]
        streams["accel"] = streams["accel"] + np.cross(a, r) + np.cross(w, np.cross(w, r))

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 3): d f / d r = [alpha]x + [omega]x [omega]x, given ``omega`` and ``alpha`` (n, 3)."""
        W = skew(np.asarray(inputs["omega"], float))
        return skew(np.asarray(inputs["alpha"], float)) + W @ W


COMPONENTS = [LeverArm()]

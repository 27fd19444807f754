"""Earth rotation: the gyro senses Earth's rate, 7.292115e-5 rad/s, with north component
Omega cos(lat) and up component Omega sin(lat) (world ENU), rotated into body axes."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase


EARTH_RATE = 7.292115e-5  # rad/s


class EarthRotationParams(Params):
    latitude_deg: float | None = Field(None, ge=-90, le=90, description="deg; default the environment's")


class EarthRotation(EffectBase):
    identifier = "earth_rotation"
    sensors = ("gyro",)
    stage = "input"
    params = EarthRotationParams
    physics = "the gyro senses Earth's rotation, whose body-frame components depend on attitude and latitude."

    def _apply(self, streams, ctx, p, rng) -> None:
        streams["gyro"] = streams["gyro"] + ctx.kin.to_body(ctx.env.earth_rate_world(p.latitude_deg))

    linear = ("latitude_deg",)  # through theta: the north and up rates it sets

    def theta(self, p) -> np.ndarray:
        lat = np.radians(p.latitude_deg if p.latitude_deg is not None else 0.0)
        return EARTH_RATE * np.array([np.cos(lat), np.sin(lat)])

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 2): d omega / d (Omega cos lat, Omega sin lat), the body-frame north and up axes;
        ``north``, ``up`` (n, 3) unit vectors in body axes."""
        return np.stack([np.asarray(inputs["north"]), np.asarray(inputs["up"])], -1)


COMPONENTS = [EarthRotation()]

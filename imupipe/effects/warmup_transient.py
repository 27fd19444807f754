"""Warm-up transient: after each power-on the bias settles as ``amp exp(-t_on / tau_s)``,
independent of temperature (``amp`` in the triad's units, ``t_on`` s since power-on)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase, Vec3


class TransientParams(Params):
    amp: Vec3 = Field(description="3, triad units")
    tau_s: float = Field(gt=0, description="s")
    sensor: Literal["accel", "gyro", "mag"] = Field("gyro", description="accel | gyro | mag")


class WarmupTransient(EffectBase):
    identifier = "warmup_transient"
    sensors = ("accel", "gyro", "mag")
    stage = "bias"
    params = TransientParams
    linear = ("amp",)
    physics = "the bias settles exponentially after power-on (electronics settling), not with temperature."

    def _apply(self, streams, ctx, p, rng) -> None:
        streams[p.sensor] = streams[p.sensor] + np.outer(np.exp(-ctx.t_on / p.tau_s), p.amp)

    def regressors(self, inputs, parameters) -> np.ndarray:
        """(n, 3, 3): d y / d amp at the given ``tau_s``, from ``t_on`` (n,) s since power-on."""
        p = self.validate(parameters)
        return np.einsum("n,ij->nij", np.exp(-np.asarray(inputs["t_on"]) / p.tau_s), np.eye(3))


COMPONENTS = [WarmupTransient()]

"""Magnetometer current interference: a periodic current (e.g. a radio transmitter) adds ``offset_T``
(sensor axes, T) during a fraction ``duty`` of every ``period_s``, starting at ``phase_s``."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase, Vec3


class CurrentParams(Params):
    offset_T: Vec3 = Field(description="3, T, sensor axes")
    period_s: float = Field(gt=0, description="s")
    duty: float = Field(gt=0, le=1, description="fraction of the period the current flows")
    phase_s: float = Field(0.0, description="s, first switch-on after the first sample")


class MagCurrentInterference(EffectBase):
    identifier = "mag_current_interference"
    sensors = ("mag",)
    stage = "bias"
    params = CurrentParams
    linear = ("offset_T",)
    physics = "a periodic current near the magnetometer adds a square-wave offset."

    def on(self, t: np.ndarray, p: CurrentParams) -> np.ndarray:
        """(n,) 1 while the current flows at times ``t`` (s from the first sample), else 0."""
        return (np.mod(np.asarray(t) - p.phase_s, p.period_s) < p.duty * p.period_s).astype(float)

    def _apply(self, streams, ctx, p, rng) -> None:
        streams["mag"] = streams["mag"] + np.outer(self.on(ctx.t - ctx.t[0], p), p.offset_T)

    def regressors(self, inputs, parameters) -> np.ndarray:
        """(n, 3, 3): d y / d offset_T given times ``t`` (n,) s and the period, duty, phase."""
        p = self.validate(parameters)
        return np.einsum("n,ij->nij", self.on(inputs["t"], p), np.eye(3))


COMPONENTS = [MagCurrentInterference()]

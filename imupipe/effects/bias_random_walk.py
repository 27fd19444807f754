"""Bias random walk: the bias wanders as a Wiener process with ``sigma`` per sqrt(s) on each axis
(triad units), restarting at zero at each power-on, beyond the white noise."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ..components import Params
from ..sim.engine import random_walk
from ._base import EffectBase, Vec3


class RandomWalkParams(Params):
    sigma: Vec3 = Field(description="3, triad units per sqrt(s)")
    sensor: Literal["accel", "gyro"] = Field("gyro", description="accel | gyro")


class BiasRandomWalk(EffectBase):
    identifier = "bias_random_walk"
    sensors = ("accel", "gyro")
    stage = "bias"
    params = RandomWalkParams
    physics = "the bias wanders slowly (flicker/rate random walk), so rests far apart disagree."

    def _apply(self, streams, ctx, p, rng) -> None:
        streams[p.sensor] = streams[p.sensor] + random_walk(ctx.t, ctx.cycle, p.sigma, rng)


COMPONENTS = [BiasRandomWalk()]

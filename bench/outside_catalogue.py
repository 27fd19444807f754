"""Effects outside the catalogue, as a third-party plugin: the proof bench's out-of-catalogue mode.

The simulator applies them through the same hook as any effect plugin (``sim.api.known_effects``):
this module is the plugin (``simulate(..., plugins=[outside_catalogue])``). ``imupipe diagnose``
does not know them (this module is not installed), so a right answer is an
``unknown`` finding, or a noise-model finding, never a catalogue name.

- ``gyro_bias_step``: the gyro bias jumps by ``step`` at ``at_fraction`` of the session (a knock,
  bias instability between rests: the memo's non-catalogue events);
- ``accel_size_effect``: each accelerometer axis's proof mass sits ``d_m`` from the centre along
  its own axis (the per-axis size effect: axis i feels ``-d (omega_j^2 + omega_k^2)``, no
  tangential term), which one common lever arm explains only in part.
"""

from __future__ import annotations

import numpy as np
import pluggy
from pydantic import Field

from imupipe.components import Params
from imupipe.effects._base import EffectBase, Vec3

hookimpl = pluggy.HookimplMarker("imupipe")


class StepParams(Params):
    step: Vec3 = Field(description="3, rad/s")
    at_fraction: float = Field(0.5, gt=0, lt=1, description="of the session's duration")


class GyroBiasStep(EffectBase):
    identifier = "gyro_bias_step"
    sensors = ("gyro",)
    stage = "bias"
    params = StepParams
    physics = "the gyro bias jumps once (a knock, bias instability)."

    def _apply(self, streams, ctx, p, rng) -> None:
        after = ctx.t >= ctx.t[0] + p.at_fraction * (ctx.t[-1] - ctx.t[0])
        streams["gyro"] = streams["gyro"] + np.outer(after, p.step)


class SizeParams(Params):
    d_m: float = Field(description="m, each axis's proof mass along its own axis")


class AccelSizeEffect(EffectBase):
    identifier = "accel_size_effect"
    sensors = ("accel",)
    stage = "input"
    params = SizeParams
    physics = "each accelerometer axis sits at its own point: axis i feels only its own centripetal part."

    def _apply(self, streams, ctx, p, rng) -> None:
        w2 = streams["accel_omega"] ** 2
        streams["accel"] = streams["accel"] - p.d_m * (w2.sum(axis=1, keepdims=True) - w2)


@hookimpl
def imupipe_register_effects(register):
    register(GyroBiasStep())
    register(AccelSizeEffect())


OUTSIDE = {"gyro_bias_step": {"step": [3e-4, -3e-4, 3e-4]}, "accel_size_effect": {"d_m": 0.005}}

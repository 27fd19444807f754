"""Magnetic field gradient: the unit was carried between places whose field differs; at place i the
field has magnitude ``levels_T[i]`` (T), same direction. |B| depends on where, not on orientation.
Places are counted by the trajectory's translations (fractional while carried); places past the
end of the list keep the last level."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ._base import EffectBase


class GradientParams(Params):
    levels_T: list[float] = Field(min_length=1, description="list, T, field magnitude at each place")


class MagFieldGradient(EffectBase):
    identifier = "mag_field_gradient"
    sensors = ("mag",)
    stage = "input"
    params = GradientParams
    physics = "the local field magnitude differs between the places the unit was recorded at."

    def level(self, place: np.ndarray, p: GradientParams) -> np.ndarray:
        """(n,) field magnitude, T, at fractional place index ``place`` (n,)."""
        return np.interp(place, np.arange(len(p.levels_T)), p.levels_T)

    def _apply(self, streams, ctx, p, rng) -> None:
        scale = self.level(ctx.kin.place, p) / ctx.env.field_T
        streams["mag"] = streams["mag"] * scale[:, None]


COMPONENTS = [MagFieldGradient()]

"""Thermal lag: the reported temperature lags the die temperature by a first-order lag of time
constant ``tau_s`` (s). The biases follow the die; the nominal model sees the lagged read-out."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params
from ..sim.sensor import first_order_lag
from ._base import EffectBase


class LagParams(Params):
    tau_s: float = Field(gt=0, description="s")


class ThermalLag(EffectBase):
    identifier = "thermal_lag"
    sensors = ("temperature",)
    stage = "temperature"
    params = LagParams
    physics = "the temperature sensor sits away from the sensing elements and lags the die temperature."

    def _apply(self, streams, ctx, p, rng) -> None:
        out = streams["T_reported"].copy()
        for c in np.unique(ctx.cycle):  # the read-out starts at the die temperature at each power-on
            m = ctx.cycle == c
            out[m] = first_order_lag(ctx.t[m], streams["T_die"][m], p.tau_s)
        streams["T_reported"] = out


COMPONENTS = [ThermalLag()]

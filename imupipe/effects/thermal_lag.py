"""Thermal lag: the reported temperature lags the die temperature by a first-order lag of time
constant ``tau_s`` (s). The biases follow the die; the nominal model sees the lagged read-out.

The lag obeys ``tau_s dT_read/dt = T_die - T_read``, so a triad whose bias follows the die as
``k (T_die - 25)`` reads ``k tau_s dT_read/dt`` more than a model of the read-out predicts:
one parameter for every triad, along its own ``k``."""

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
    linear = ("tau_s",)
    physics = "the temperature sensor sits away from the sensing elements and lags the die temperature."

    def _apply(self, streams, ctx, p, rng) -> None:
        out = streams["T_reported"].copy()
        for c in np.unique(ctx.cycle):  # the read-out starts at the die temperature at each power-on
            m = ctx.cycle == c
            out[m] = first_order_lag(ctx.t[m], streams["T_die"][m], p.tau_s)
        streams["T_reported"] = out

    def regressors(self, inputs) -> np.ndarray:
        """(n, 3, 1): d y / d tau_s given the triad's bias temperature coefficient ``k`` (3,) or
        (n, 3), triad units per degC, and the read-out's rate ``T_rate`` (n,) degC/s."""
        rate = np.asarray(inputs["T_rate"], float)
        return (np.broadcast_to(np.asarray(inputs["k"], float), (len(rate), 3)) * rate[:, None])[:, :, None]


COMPONENTS = [ThermalLag()]

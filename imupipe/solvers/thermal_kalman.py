"""Method A thermal fit: the identification Kalman filter of the warm-up (Vyalkov 2023).

State ``Y = (b0x, b0y, b0z, kx, ky, kz)``, ``F = I``, ``Q = 0``, ``P0 = I``,
``H_i = [I | (T_i - 25) I]``, ``R = diag(sigma^2)``: recursive least squares for a
constant state. For accel and mag the first three states hold the projection of
g or B and only ``k`` is meaningful.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..components import Params
from ..errors import SolverError
from ..observations import ThermalFit, ThermalObservations

MIN_SPAN_C = 2.0  # a warm-up spanning less than this cannot separate k from b0


class ThermalKalmanParams(Params):
    """``p0``: initial state variance (the paper's P0 = I, in sensor units^2);
    ``min_span_C``: refuse warm-ups with a smaller temperature span."""

    p0: float = 1.0
    min_span_C: float = MIN_SPAN_C


def check_span(obs: ThermalObservations, min_span: float) -> float:
    span = float(np.nanmax(obs.T) - np.nanmin(obs.T)) if len(obs.T) else 0.0
    if len(obs.T) < 6 or not np.isfinite(span) or span < min_span:
        raise SolverError(
            f"{obs.sensor} thermal fit: the warm-up spans {span:.2f} degC over {len(obs.T)} averages; "
            f"k needs a rest with at least {min_span} degC of self-heating (the paper uses 1 h, "
            "about 20 degC): record a longer warm-up or drop the thermal stage"
        )
    return span


class ThermalKalman:
    """``solve(ThermalObservations) -> ThermalFit`` with the filter's covariance."""

    name = "thermal_kalman"
    kind = "thermal"
    version = "1"
    params: ClassVar[type[Params]] = ThermalKalmanParams

    def solve(self, obs: ThermalObservations, params: ThermalKalmanParams) -> ThermalFit:
        span = check_span(obs, params.min_span_C)
        Y = np.zeros(6)
        P = np.eye(6) * params.p0
        R = np.diag(np.asarray(obs.sigma, dtype=float) ** 2)
        I3 = np.eye(3)
        for T, x in zip(obs.T, obs.y, strict=True):
            H = np.hstack([I3, (T - obs.T_ref_C) * I3])
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T  # P H^T S^-1 (P, S symmetric)
            Y = Y + K @ (x - H @ Y)
            P = (np.eye(6) - K @ H) @ P
            P = 0.5 * (P + P.T)
        dT = obs.T - obs.T_ref_C
        resid = obs.y - (Y[:3] + np.outer(dT, Y[3:]))
        return ThermalFit(Y[:3], Y[3:], P, {
            "T_span_C": span, "n_averages": len(obs.T), "sigma": np.asarray(obs.sigma).tolist(),
            "residual_rms": np.sqrt(np.mean(resid**2, axis=0)).tolist(), "law": "linear",
        })


COMPONENTS = [ThermalKalman()]

"""Method A thermal fit: the identification Kalman filter of the warm-up (Vyalkov 2023).

State ``Y = (b0x, b0y, b0z, kx, ky, kz)``, ``F = I``, ``Q = 0``,
``H_i = [I | (T_i - 25) I]``, ``R = diag(sigma^2)``: recursive least squares for a
constant state. It runs in information form (``P^-1`` and ``P^-1 Y`` accumulate
``H^T R^-1 H`` and ``H^T R^-1 y``), which gives the covariance-form filter's last
step exactly and allows the diffuse start ``P0^-1 = 0``: the estimate is then batch
least squares whatever the units. The paper's ``P0 = I`` is in its normalised units
(g, deg/h); ``p0`` reproduces it with each axis normalised by its largest reading.
For accel and mag the first three states hold the projection of g or B and only
``k`` is meaningful.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from ..components import Params
from ..errors import SolverError
from ..observations import ThermalFit, ThermalObservations

MIN_SPAN_C = 2.0  # a warm-up spanning less than this cannot separate k from b0


class ThermalKalmanParams(Params):
    """``p0``: None for a diffuse start (batch least squares), or the initial state
    variance ``P0 = p0 I`` in units normalised per axis by the largest reading (the
    paper's ``P0 = I``: a zero-mean prior of that size); ``min_span_C``: refuse
    warm-ups with a smaller temperature span (degC)."""

    p0: float | None = Field(None, gt=0)
    min_span_C: float = Field(MIN_SPAN_C, gt=0)


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
    version = "2"  # 2: information form, diffuse or normalised prior (any units)
    params: ClassVar[type[Params]] = ThermalKalmanParams

    def solve(self, obs: ThermalObservations, params: ThermalKalmanParams) -> ThermalFit:
        span = check_span(obs, params.min_span_C)
        dT = obs.T - obs.T_ref_C
        # per-axis unit: the largest reading, so b0 is O(1) and P0 = p0 I means the same in
        # counts, m/s^2 or T
        unit = np.max(np.abs(obs.y), axis=0)
        unit = np.where(unit > 0, unit, 1.0)
        w = 1.0 / (np.asarray(obs.sigma, dtype=float) / unit) ** 2  # R^-1, normalised
        z = obs.y / unit
        # information: sum over the averages of H_i^T R^-1 H_i and H_i^T R^-1 z_i, per axis
        n, s1, s2 = len(dT), dT.sum(), dT @ dT
        info = np.zeros((6, 6))
        vec = np.zeros(6)
        for ax in range(3):
            info[np.ix_([ax, 3 + ax], [ax, 3 + ax])] = w[ax] * np.array([[n, s1], [s1, s2]])
            vec[[ax, 3 + ax]] = w[ax] * np.array([z[:, ax].sum(), dT @ z[:, ax]])
        if params.p0 is not None:
            info += np.eye(6) / params.p0  # the prior Y0 = 0, P0 = p0 I
        try:
            P_n = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            raise SolverError(f"{obs.sensor} thermal fit: the warm-up does not separate k from "
                              "b0 (singular information); record a warm-up with heating") from None
        P_n = 0.5 * (P_n + P_n.T)
        D = np.concatenate([unit, unit])  # back to sensor units
        Y = D * (P_n @ vec)
        P = P_n * np.outer(D, D)
        resid = obs.y - (Y[:3] + np.outer(dT, Y[3:]))
        return ThermalFit(Y[:3], Y[3:], P, {
            "prior": "diffuse" if params.p0 is None else f"P0 = {params.p0} I, normalised",
            "T_span_C": span, "n_averages": len(obs.T), "sigma": np.asarray(obs.sigma).tolist(),
            "residual_rms": np.sqrt(np.mean(resid**2, axis=0)).tolist(), "law": "linear",
        })


COMPONENTS = [ThermalKalman()]

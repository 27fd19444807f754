"""Polynomial bias-temperature law (PX4-like cubic), an alternative to the Kalman filter.

``b(T) = c0 + c1 dT + c2 dT^2 + c3 dT^3``, ``dT = T - 25``, fitted per axis by
weighted least squares. ``k`` is reported as the slope at 25 degC (``c1``) so the
nominal linear model uses it; the full coefficients are in ``details``.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from ..components import Params
from ..observations import ThermalFit, ThermalObservations
from .thermal_kalman import MIN_SPAN_C, check_span


class ThermalPolyParams(Params):
    """``degree``: 1 (linear LS, equal to the filter with a flat prior) to 3 (PX4)."""

    degree: int = Field(3, ge=1, le=3)
    min_span_C: float = Field(MIN_SPAN_C, gt=0)


class ThermalPoly:
    name = "thermal_poly"
    kind = "thermal"
    version = "1"
    params: ClassVar[type[Params]] = ThermalPolyParams

    def solve(self, obs: ThermalObservations, params: ThermalPolyParams) -> ThermalFit:
        span = check_span(obs, params.min_span_C)
        dT = obs.T - obs.T_ref_C
        A = np.vander(dT, params.degree + 1, increasing=True)
        coef, *_ = np.linalg.lstsq(A, obs.y, rcond=None)  # (degree+1, 3)
        resid = obs.y - A @ coef
        sig2 = np.asarray(obs.sigma, dtype=float) ** 2
        AtA_inv = np.linalg.pinv(A.T @ A)
        cov = np.zeros((6, 6))
        for ax in range(3):
            cov[ax, ax] = sig2[ax] * AtA_inv[0, 0]
            cov[3 + ax, 3 + ax] = sig2[ax] * AtA_inv[1, 1]
            cov[ax, 3 + ax] = cov[3 + ax, ax] = sig2[ax] * AtA_inv[0, 1]
        return ThermalFit(coef[0], coef[1], cov, {
            "T_span_C": span, "n_averages": len(obs.T), "law": f"polynomial degree {params.degree}",
            "coefficients": coef.T.tolist(), "residual_rms": np.sqrt(np.mean(resid**2, 0)).tolist(),
        })


COMPONENTS = [ThermalPoly()]

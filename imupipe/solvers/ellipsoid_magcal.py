"""Magnetometer hard and soft iron alone: the ellipsoid of a free tumble (MATLAB ``magcal``'s job).

The readings of a constant field seen from every direction lie on an ellipsoid
``(y - b)^T A (y - b) = r^2``. The fit is method A's linear least squares
(``ellipsoid_cholesky.fit_ellipsoid``, on centred points); the correction is
``M = beta * Q L^T`` with ``Q`` the rotation that makes it symmetric: the soft
iron matrix with no rotation of the sensor axes, as ``magcal``'s ``"sym"`` fit.
Nothing ties the magnetometer to another sensor (no gravity, no rests needed);
``M`` scales the corrected field to ``obs.magnitude``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import ClassVar

import numpy as np
from pydantic import Field

from ..components import Params
from ..observations import EllipsoidObservations, TriadFit
from .ellipsoid_cholesky import MIN_COVERAGE, MIN_POSITIONS, EllipsoidCholesky, EllipsoidParams


class MagcalParams(Params):
    """``min_positions``, ``min_coverage``: refusal thresholds of the ellipsoid fit."""

    min_positions: int = Field(MIN_POSITIONS, ge=9)
    min_coverage: float = Field(MIN_COVERAGE, ge=0, le=1)


class EllipsoidMagcal:
    """Magnetometer solver: ``solve(EllipsoidObservations) -> TriadFit``; ignores ``gravity``."""

    name = "ellipsoid_magcal"
    kind = "mag"
    version = "1"
    params: ClassVar[type[Params]] = MagcalParams

    def solve(self, obs: EllipsoidObservations, params: MagcalParams) -> TriadFit:
        fit = EllipsoidCholesky().solve(
            replace(obs, y_up=None, x_up=None, gravity=None),
            EllipsoidParams(canonical_frame="symmetric", min_positions=params.min_positions,
                            min_coverage=params.min_coverage))
        x = (obs.y - fit.b0) @ np.asarray(fit.M).T
        norm = np.linalg.norm(x, axis=1) / obs.magnitude
        details = {**fit.details, "frame": "symmetric soft iron (no rotation; magcal's 'sym')",
                   "field_norm_residual_rms": float(np.sqrt(np.mean((norm - 1) ** 2)))}
        return TriadFit(fit.M, fit.b0, fit.cov, details)


COMPONENTS = [EllipsoidMagcal()]

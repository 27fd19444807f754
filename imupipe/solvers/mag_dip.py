"""Method A magnetometer: ellipsoid, then rotation and scale tied to gravity by the dip (eqs. 21-25).

The corrected gravity and the field keep a constant dot product, the field's
vertical component ``B1 = -sin(dip)`` (normal frame Y up, field pointing down
in the northern hemisphere). Eqs. (22)-(23) solve a general 3x3 matrix; it is
projected to the nearest rotation, and the scale is eq. (24).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from ..components import Params
from ..errors import SolverError
from ..observations import EllipsoidObservations, TriadFit
from ..rotations import nearest_rotation
from .ellipsoid_cholesky import (
    MIN_COVERAGE,
    MIN_POSITIONS,
    coverage,
    fit_ellipsoid,
    jacobian,
)


class MagDipParams(Params):
    """``min_positions``, ``min_coverage``: refusal thresholds of the ellipsoid fit."""

    min_positions: int = Field(MIN_POSITIONS, ge=9)
    min_coverage: float = Field(MIN_COVERAGE, ge=0, le=1)


def circle_dip(unit_fields: list[np.ndarray]) -> tuple[float, list[float]]:
    """Dip (rad) from turntable circles: ``pi/2 - asin(mean R_i)`` (paper, Fig. 4c).

    Each item: (k, 3) unit field vectors over one or more full turns of the rig base.
    They lie where the unit sphere meets a plane ``n . x = h`` (n from the points'
    scatter), so the radius is ``sqrt(1 - h^2)``: unlike a centroid-based radius,
    this does not depend on how evenly the samples spread around the turn.
    """
    radii = []
    for pts in unit_fields:
        _, _, Vt = np.linalg.svd(pts - pts.mean(axis=0))
        h = float(np.mean(pts @ Vt[2]))
        radii.append(float(np.sqrt(max(1.0 - h * h, 0.0))))
    return float(np.pi / 2 - np.arcsin(np.clip(np.mean(radii), 0, 1))), radii


class MagDip:
    """Magnetometer solver of method A: ``solve(EllipsoidObservations) -> TriadFit``.

    Needs ``obs.gravity`` (corrected unit gravity per rest). The dip is
    ``obs.dip_rad`` when given (the stage measures it from turntable circles with
    ``circle_dip``), else estimated from the rests themselves: the LS of eq. (23)
    with ``B1 = 1`` gives ``R / (rho B1)``, whose size fixes ``B1``.
    """

    name = "ellipsoid_dip"
    kind = "mag"
    version = "2"  # 2: ellipsoid fit on centred points (hard iron beyond the field)
    params: ClassVar[type[Params]] = MagDipParams

    def solve(self, obs: EllipsoidObservations, params: MagDipParams) -> TriadFit:
        if obs.gravity is None:
            raise SolverError(
                "mag: the dip-angle rotation (eqs. 21-23) needs the corrected accelerometer at the "
                "same rests; wire the accel calibration into the mag stage"
            )
        shape = fit_ellipsoid(obs.y, "mag", params.min_positions, params.min_coverage)
        u = obs.y / shape.scale
        g = obs.gravity / np.linalg.norm(obs.gravity, axis=1, keepdims=True)

        def solve_from(d: np.ndarray, r_fixed: np.ndarray | None = None):
            """(Mn, b, info) for ellipsoid vector ``d``; ``r_fixed`` replaces the LS of eq. (23)."""
            b, L, _ = shape.geometry(d)
            B_hat = (u - b) @ L  # rows: L^T (m - b), analogue of eq. (17)
            V = np.einsum("ki,kj->kij", g, B_hat).reshape(len(u), 9)  # Eq. (22): rows m_k
            target = -np.sin(obs.dip_rad) if obs.dip_rad is not None else 1.0
            r, *_ = np.linalg.lstsq(V, np.full(len(u), target), rcond=None)  # Eq. (23)
            res = np.full(len(u), target) - V @ r
            r_cov = float(res @ res) / max(len(u) - 9, 1) * np.linalg.pinv(V.T @ V)
            r = r if r_fixed is None else r_fixed
            if obs.dip_rad is not None:
                B1, dip_source = target, "given"
                A = r.reshape(3, 3)
            else:
                A1 = r.reshape(3, 3)
                # A1 = R / (rho B1): its singular values give 1 / (rho |B1|), sign from det
                sv = np.linalg.svd(A1, compute_uv=False).mean()
                rho_fit = np.mean(np.linalg.norm(B_hat, axis=1))
                B1 = float(np.sign(np.linalg.det(A1)) / (sv * rho_fit))
                A = A1 * B1
                dip_source = "estimated from the rests"
            R = nearest_rotation(A)
            beta = len(u) / np.sum(np.linalg.norm(B_hat, axis=1))  # Eq. (24)
            Mn = beta * R @ L.T  # Eq. (25)
            return Mn, b * shape.scale, {"B1": float(B1), "dip_source": dip_source,
                                         "beta": float(beta), "r": r, "r_cov": r_cov}

        Mn, b, info = solve_from(shape.d)
        unit = obs.magnitude / shape.scale
        M = unit * Mn

        def pack(d: np.ndarray) -> np.ndarray:
            m, bb, _ = solve_from(d)
            return np.concatenate([(unit * m).ravel(), bb])

        cov = (J := jacobian(pack, shape.d)) @ shape.d_cov @ J.T
        r_hat, r_cov = info.pop("r"), info.pop("r_cov")

        def pack_r(r: np.ndarray) -> np.ndarray:
            m, bb, _ = solve_from(shape.d, r)
            return np.concatenate([(unit * m).ravel(), bb])

        cov = cov + (J_r := jacobian(pack_r, r_hat)) @ r_cov @ J_r.T  # the rotation LS (23) too
        corrected = (obs.y - b) @ M.T / obs.magnitude
        dots = np.sum(corrected * g, axis=1)
        details = {
            **info, "dip_deg": float(np.degrees(np.arcsin(np.clip(-info["B1"], -1, 1)))),
            "dot_residual_rms": float(np.std(dots - info["B1"])),
            "n_positions": len(obs.y), "coverage": coverage(obs.y - b),
            "algebraic_residual_rms": shape.residual_rms, "magnitude": obs.magnitude,
            "normalised": obs.magnitude == 1.0,
        }
        return TriadFit(M, b, cov, details)


COMPONENTS = [MagDip()]

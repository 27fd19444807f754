"""Method A ellipsoid: linear LS with D33 = 0, Cholesky, reference rotation (Vyalkov 2023).

The rest means of a constant-magnitude vector lie on an ellipsoid; eqs. (7)-(13)
fit it linearly, (15) factors its shape, (16)-(20) fix scale and rotation from
the reference positions (instrument Y up / X up). Work is done in units of the
vector's magnitude (the paper's unit g) and returned in SI.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from ..components import Params
from ..errors import SolverError
from ..observations import EllipsoidObservations, TriadFit
from ..rotations import frame_from_up_vectors, nearest_rotation

MIN_POSITIONS = 12  # 9 unknowns + margin: below this the fit is not trustworthy
MIN_COVERAGE = 0.35  # smallest eigenvalue of the direction scatter (0.333 = uniform sphere)


@dataclass(frozen=True)
class EllipsoidShape:
    """Normalised ellipsoid: ``u = y / scale``; ``(u - b)^T D0 (u - b) = rho^2`` (eq. 13).

    The LS (eq. 12) runs on the points less their mean ``centre`` (3,), raw units:
    the D33 = 0 form (right-hand side 1) needs the origin inside the ellipsoid,
    which raw counts or a hard iron larger than the field break. ``d`` the 9 LS
    unknowns (eq. 11) of the centred points, ``d_cov`` (9, 9) their covariance
    from the normal equations; ``b`` (3,) the centre in units of ``u`` (the raw
    offset is ``b * scale``); ``L`` lower Cholesky factor of ``D0`` (eq. 15).
    """

    centre: np.ndarray
    scale: float
    d: np.ndarray
    d_cov: np.ndarray
    D0: np.ndarray
    b: np.ndarray
    L: np.ndarray
    rho: float
    residual_rms: float

    def geometry(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(b (3,) in units of ``u``, L (3, 3), rho) for an LS vector ``d`` of the centred
        points: ``shape_from_d`` with the centre added back."""
        _, b, L, rho = shape_from_d(d)
        return self.centre / self.scale + b, L, rho


def design_row(u: np.ndarray) -> np.ndarray:
    """(n, 9) rows ``s`` of eq. (11) for points ``u`` (n, 3)."""
    x, y, z = u.T
    return np.column_stack([x * x, 2 * x * y, y * y, 2 * x * z, 2 * y * z, z * z, 2 * x, 2 * y, 2 * z])


def shape_from_d(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """D0 (3, 3), b (3,), L (3, 3), rho from the LS vector ``d`` (eqs. 9, 13, 15)."""
    D0 = np.array([[d[0], d[1], d[3]], [d[1], d[2], d[4]], [d[3], d[4], d[5]]])
    D1 = d[6:9]
    try:
        L = np.linalg.cholesky(D0)  # Eq. (15)
    except np.linalg.LinAlgError:
        raise SolverError(
            "the ellipsoid fit is not positive definite: the rests do not outline an ellipsoid "
            "(too few distinct orientations, or motion inside the rests); record more positions "
            "spread over the whole sphere"
        ) from None
    b = -np.linalg.solve(D0, D1)  # Eq. (13)
    rho = float(np.sqrt(1.0 + b @ D0 @ b))  # D33 = 0 leaves the sphere radius at rho, not 1
    return D0, b, L, rho


def coverage(directions: np.ndarray) -> float:
    """3 x smallest eigenvalue of the mean outer product of unit ``directions`` (1 = uniform)."""
    u = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    return float(3 * np.linalg.eigvalsh(u.T @ u / len(u))[0])


def fit_ellipsoid(y: np.ndarray, what: str, min_positions: int = MIN_POSITIONS,
                  min_coverage: float = MIN_COVERAGE) -> EllipsoidShape:
    """Eqs. (10)-(15) on raw points ``y`` (n, 3); ``what`` names the sensor in errors."""
    n = len(y)
    if n < min_positions:
        raise SolverError(
            f"{what}: only {n} rest positions; the ellipsoid has 9 unknowns and needs at least "
            f"{min_positions} distinct orientations (the paper uses >= 200): record more positions"
        )
    centred = y - y.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))
    cov_q = coverage(centred)
    if cov_q < min_coverage:
        raise SolverError(
            f"{what}: the {n} positions cover the sphere poorly (coverage {cov_q:.2f}, need "
            f">= {min_coverage}); add positions with the missing axes pointing up and down"
        )
    centre = y.mean(axis=0)
    u = centred / scale  # origin inside the ellipsoid whatever the offset
    V = design_row(u)
    G = np.ones(n)
    d, *_ = np.linalg.lstsq(V, G, rcond=None)  # Eq. (12)
    r = G - V @ d
    dof = max(n - 9, 1)
    s2 = float(r @ r / dof)
    d_cov = s2 * np.linalg.pinv(V.T @ V)
    D0, b, L, rho = shape_from_d(d)
    return EllipsoidShape(centre, scale, d, d_cov, D0, centre / scale + b, L, rho,
                          float(np.sqrt(s2)))


def jacobian(f, x: np.ndarray, rel: float = 1e-7) -> np.ndarray:
    """Forward-difference Jacobian of ``f`` (m,) at ``x`` (n,)."""
    f0 = np.asarray(f(x), dtype=float)
    J = np.empty((f0.size, x.size))
    for i in range(x.size):
        h = rel * max(abs(x[i]), 1e-3)
        xp = x.copy()
        xp[i] += h
        J[:, i] = (np.asarray(f(xp), dtype=float) - f0) / h
    return J


class EllipsoidParams(Params):
    """``canonical_frame`` when no reference positions: ``symmetric`` (M = M^T, the
    smallest turn from the sensor axes) or ``upper_triangular`` (the paper's L^T alone).
    ``scale_from``: ``fit`` (rho from all rests) or ``reference`` (the paper's eq. 18:
    1/|g| of the Y-up rest). ``min_positions``, ``min_coverage``: refusal thresholds."""

    canonical_frame: Literal["symmetric", "upper_triangular"] = "symmetric"
    scale_from: Literal["fit", "reference"] = "fit"
    min_positions: int = Field(MIN_POSITIONS, ge=9)
    min_coverage: float = Field(MIN_COVERAGE, ge=0, le=1)


def correction(shape: EllipsoidShape, d: np.ndarray, obs: EllipsoidObservations,
               p: EllipsoidParams) -> tuple[np.ndarray, np.ndarray, dict]:
    """M (normalised, eq. 20) and b (raw units) for LS vector ``d``."""
    b, L, rho = shape.geometry(d)
    u = obs.y / shape.scale
    if obs.y_up is not None:
        g_hat = L.T @ (u[obs.y_up] - b)  # Eq. (17)
        g_x = L.T @ (u[obs.x_up] - b) if obs.x_up is not None else None  # Eq. (19)
        R = frame_from_up_vectors(g_hat, g_x)  # Eqs. (18)-(19) without angle wrap-round
        beta = 1.0 / np.linalg.norm(g_hat) if p.scale_from == "reference" else 1.0 / rho
        frame = "reference positions" + ("" if obs.x_up is not None else " (Y up only)")
    elif p.canonical_frame == "symmetric":
        R = nearest_rotation(L)  # L = Q P (polar): Q L^T = Q P Q^T is symmetric
        beta, frame = 1.0 / rho, "symmetric"
    else:
        R, beta, frame = np.eye(3), 1.0 / rho, "upper_triangular"
    Mn = beta * R @ L.T  # Eq. (16), (20)
    return Mn, b * shape.scale, {"frame": frame, "beta": beta}


class EllipsoidCholesky:
    """Accelerometer solver of method A: ``solve(EllipsoidObservations) -> TriadFit``."""

    name = "ellipsoid_cholesky"
    kind = "accel"
    version = "2"  # 2: fit on centred points (offsets beyond the radius)
    params: ClassVar[type[Params]] = EllipsoidParams

    def solve(self, obs: EllipsoidObservations, params: EllipsoidParams) -> TriadFit:
        shape = fit_ellipsoid(obs.y, obs.sensor, params.min_positions, params.min_coverage)
        Mn, b, info = correction(shape, shape.d, obs, params)
        unit = obs.magnitude / shape.scale  # normalised M -> SI: x = magnitude * Mn * (y - b) / scale
        M = unit * Mn

        def pack(d: np.ndarray) -> np.ndarray:
            m, bb, _ = correction(shape, d, obs, params)
            return np.concatenate([(unit * m).ravel(), bb])

        J = jacobian(pack, shape.d)
        cov = J @ shape.d_cov @ J.T
        refs = [i for i in (obs.y_up, obs.x_up) if i is not None]
        if refs and obs.cov is not None:
            # the frame also carries the noise of the reference rests' own means
            def pack_refs(v: np.ndarray) -> np.ndarray:
                y = obs.y.copy()
                y[refs] = v.reshape(len(refs), 3)
                m, bb, _ = correction(shape, shape.d, replace(obs, y=y), params)
                return np.concatenate([(unit * m).ravel(), bb])

            J_r = jacobian(pack_refs, obs.y[refs].ravel())
            cov_r = np.zeros((3 * len(refs),) * 2)
            for k, i in enumerate(refs):
                cov_r[3 * k:3 * k + 3, 3 * k:3 * k + 3] = obs.cov[i]
            cov = cov + J_r @ cov_r @ J_r.T
        details = {
            **info, "n_positions": len(obs.y), "coverage": coverage(obs.y - b),
            "algebraic_residual_rms": shape.residual_rms, "rho": shape.rho,
            "magnitude": obs.magnitude, "L": shape.L.tolist(),
        }
        return TriadFit(M, b, cov, details)


COMPONENTS = [EllipsoidCholesky()]

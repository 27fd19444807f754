"""Accelerometer, method B (Chikrin & Golousov 2021): the gravity quadric solved by SVD.

Every rest gives ``|g|^2 = (a - b)^T W (a - b)`` with ``W = (MS)^-T (MS)^-1``
(Eq. (2.2)-(2.4)), linear in the ten quadric coefficients ``alpha`` (Eq. (2.6)-(2.8)).
Stacking the rests gives ``F alpha = 0`` (Eq. (2.9)), solved by the right singular
vector of the smallest singular value. ``W`` and ``b`` follow from Eq. (2.10), ``g``
from Eq. (2.11), ``alpha`` is rescaled (Eq. (2.12)) so that the corrected vector has
the local gravity's length, and ``MS`` is a square root of ``W^-1`` (Eq. (2.13)).

Gravity alone fixes ``W``, i.e. ``MS`` up to a rotation: ``MS Q`` for any orthogonal
``Q`` fits equally well. The paper fixes it by its frame ``A0`` (x along the
accelerometer's x axis, y in its xy plane), i.e. ``MS`` lower-triangular (Eq. (1.3)):
the Cholesky factor of ``W^-1``. ``square_root = "symmetric"`` takes the principal
root instead (the frame closest to the sensor's own axes); ``"upper_correction"``
makes the correction ``M`` upper-triangular, imu_tk's ``T K`` (Tedaldi 2014).

In imupipe's notation the forward matrix is ``S = MS`` and the correction ``M = S^-1``.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np

from ..components import Params
from ..errors import SolverError
from ..observations import EllipsoidObservations, TriadFit
from .triad_covariance import ellipsoid_uncertainty

MIN_RESTS = 9  # nine independent constants: W (6) and b (3)
MIN_RESTS_DIAGONAL = 6  # without misalignment: three scales and three biases
FORMS = {"cholesky": "lower", "symmetric": "symmetric", "upper_correction": "upper"}  # free entries of S


class EllipsoidSVDParams(Params):
    square_root: Literal["cholesky", "symmetric", "upper_correction"] = "cholesky"
    """How ``MS = sqrt(W^-1)`` picks the frame: lower-triangular (Eq. (1.3)), symmetric, or
    the correction upper-triangular (imu_tk's convention)."""
    misalignment: bool = True
    """False: axis-aligned ellipsoid (``S^A = I``, 6 constants, Eq. (2.7) without the cross
    terms); for protocols with six poses only (Ferraris), which cannot fix nine."""


def quadric_rows(a: np.ndarray) -> np.ndarray:
    """The rows ``f(a)`` of Eq. (2.7): (n, 10) from readings ``a`` (n, 3)."""
    x, y, z = a.T
    one = np.ones_like(x)
    return np.column_stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z, one])


def quadric_to_W_b(alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``W`` (3, 3), ``b`` (3,) and ``g^2`` from the ten coefficients, Eq. (2.10)-(2.11).

    The cross terms of Eq. (2.5) appear once per pair, so ``alpha_4..6`` are ``2 W_ij``
    when ``f`` carries ``x y`` (not ``2 x y``): halve them here.
    """
    a1, a2, a3, a4, a5, a6, a7, a8, a9, a10 = alpha
    W = np.array([[a1, a4 / 2, a5 / 2], [a4 / 2, a2, a6 / 2], [a5 / 2, a6 / 2, a3]])  # Eq. (2.10)
    b = -0.5 * np.linalg.solve(W, np.array([a7, a8, a9]))
    g2 = float(b @ W @ b - a10)  # Eq. (2.11)
    return W, b, g2


def fit_quadric(y: np.ndarray, magnitude: float,
                misalignment: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``W`` (3, 3) 1/unit^2, ``b`` (3,) and the smallest singular values, from rests ``y`` (n, 3).

    The readings are centred and scaled to O(1) first so that the columns of ``F``
    are comparable; the quadric is mapped back exactly afterwards. Without
    ``misalignment`` the cross terms are left out (an axis-aligned ellipsoid).
    """
    c = y.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((y - c) ** 2, axis=1))))
    u = (y - c) / s
    F = quadric_rows(u)
    cols = np.arange(10) if misalignment else np.array([0, 1, 2, 6, 7, 8, 9])
    _, sv, vt = np.linalg.svd(F[:, cols], full_matrices=True)  # Eq. (2.9); vt square
    alpha = np.zeros(10)
    alpha[cols] = vt[-1]
    W_u, b_u, g2 = quadric_to_W_b(alpha)
    if g2 == 0 or not np.isfinite(g2):
        raise SolverError("ellipsoid_svd: the rests do not determine a quadric; record rests "
                          "that cover the whole sphere of orientations")
    alpha = alpha / g2  # Eq. (2.12), then (2.10) again
    W_u, b_u, _ = quadric_to_W_b(alpha)
    # (a - b_a)^T W_a (a - b_a) = magnitude^2 with a = s u + c.
    W = W_u * magnitude**2 / s**2
    b = c + s * b_u
    return W, b, sv


def square_root_inverse(W: np.ndarray, how: str) -> np.ndarray:
    """``MS`` with ``MS MS^T = W^-1``, Eq. (2.13): lower-triangular or symmetric."""
    try:
        if how == "cholesky":
            return np.linalg.cholesky(np.linalg.inv(W))
        if how == "upper_correction":  # W = M^T M with M = L^T upper-triangular
            return np.linalg.inv(np.linalg.cholesky(W).T)
        from scipy.linalg import sqrtm  # here: the other roots need no scipy.linalg

        return np.real(sqrtm(np.linalg.inv(W)))
    except np.linalg.LinAlgError:
        raise SolverError("ellipsoid_svd: the fitted quadric is not an ellipsoid (W not positive "
                          "definite); the rests are too few or too clustered, record positions "
                          "spread over the whole sphere") from None


def scale_and_misalignment(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split the forward matrix ``S = M^A S^A`` into scales (3,) and unit-diagonal S^A, Eq. (1.3)-(1.4)."""
    m = np.diag(S).copy()
    return m, S / m[:, None]


class EllipsoidSVD:
    """Solver ``ellipsoid_svd`` (kind ``accel``): Chikrin & Golousov's quadric fit."""

    name = "ellipsoid_svd"
    kind = "accel"
    version = "1"
    params: ClassVar[type[Params]] = EllipsoidSVDParams

    def solve(self, observations: EllipsoidObservations, params: EllipsoidSVDParams) -> TriadFit:
        y = np.asarray(observations.y, dtype=float)
        n = len(y)
        need = MIN_RESTS if params.misalignment else MIN_RESTS_DIAGONAL
        if n < need:
            raise SolverError(
                f"ellipsoid_svd: {n} rests for {need} accelerometer constants; record at least "
                f"{need - n} more distinct static positions (20 or more spread over the sphere "
                "for useful uncertainties)"
                + ("" if not params.misalignment else
                   ", or fit scales and biases only with solver_params misalignment = false")
            )
        g = float(observations.magnitude)
        W, b, sv = fit_quadric(y, g, params.misalignment)
        if np.linalg.eigvalsh(W).min() <= 0:
            raise SolverError("ellipsoid_svd: the fitted quadric is not an ellipsoid (W not positive "
                              "definite); the rests are too few or too clustered, record positions "
                              "spread over the whole sphere (each axis up and down)")
        if params.misalignment:
            S, form = square_root_inverse(W, params.square_root), FORMS[params.square_root]
        else:
            S, form = np.diag(1.0 / np.sqrt(np.diag(W))), "diagonal"
        M = np.linalg.inv(S)
        fit = ellipsoid_uncertainty(y, np.asarray(observations.cov, float), M, b, g, form=form)
        cov12 = fit.pop("cov12")
        scales, misalignment = scale_and_misalignment(S)
        details = {
            **fit,
            "paper_scale": scales.tolist(),
            "paper_misalignment": misalignment.tolist(),
            "singular_values_tail": sv[-3:].tolist(),
            "square_root": params.square_root if params.misalignment else "diagonal",
            "magnitude": g,
        }
        return TriadFit(M, b, cov12, details)


COMPONENTS = [EllipsoidSVD()]

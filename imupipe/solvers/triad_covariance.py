"""Linearised uncertainties shared by the method-B solvers.

Gauss-Newton covariance ``(J^T W J)^-1`` of the parameters at the optimum, with
``W`` the inverse noise covariance of the residuals, then mapped to imupipe's
layout: ``(M.ravel(), b0)`` (12) with ``M = S^-1`` the correction matrix.
When the fit's chi-square per degree of freedom exceeds one (model error the
noise does not explain) the covariance is inflated by it, so the reported
sigmas never claim more than the residuals support.
"""

from __future__ import annotations

import numpy as np


def shape_basis(form: str = "lower") -> np.ndarray:
    """(p, 3, 3) basis of the free entries of ``S``: ``lower``/``upper`` triangular or
    ``symmetric`` (p = 6), or ``diagonal`` (p = 3)."""
    if form == "diagonal":
        return np.array([np.diag(e) for e in np.eye(3)])
    basis = []
    for j in range(3):
        for k in range(j + 1):
            E = np.zeros((3, 3))
            E[j, k] = 1.0
            if form == "symmetric":
                E[k, j] = 1.0
            basis.append(E.T if form == "upper" else E)
    return np.array(basis)


def gauss_newton_cov(J: np.ndarray, chi2: float, dof: int) -> tuple[np.ndarray, float]:
    """``(J^T J)^-1`` of a whitened Jacobian (n, p), inflated by ``max(1, chi2/dof)``."""
    cov = np.linalg.pinv(J.T @ J)
    inflation = max(1.0, chi2 / dof) if dof > 0 else 1.0
    return cov * inflation, inflation


def ellipsoid_uncertainty(y: np.ndarray, cov: np.ndarray, M: np.ndarray, b: np.ndarray,
                          g: float, form: str = "lower") -> dict:
    """Covariance of an ellipsoid fit from the radial residuals ``|M (y - b)| - g``.

    ``y`` (n, 3) rest means, ``cov`` (n, 3, 3) their covariances (sensor units^2),
    ``M`` (3, 3), ``b`` (3,), ``g`` the magnitude. Returns ``cov12`` (12, 12) over
    ``(M.ravel(), b)``, ``rms_residual`` (sensor units), ``chi2``, ``dof`` and
    ``inflation``.
    """
    x = (y - b) @ M.T
    r = np.linalg.norm(x, axis=1)
    nrm = x / r[:, None]
    sigma = np.sqrt(np.einsum("ni,ij,njk,lk,nl->n", nrm, M, cov, M, nrm))
    sigma = np.maximum(sigma, 1e-300)
    nM = nrm @ M  # (n, 3): d|x|/dy
    E = shape_basis(form)
    # d|x|/dS_k = -n^T M E_k x (x = S^-1 (y - b)); d|x|/db = -n^T M.
    J_S = -np.einsum("ni,kij,nj->nk", nM, E, x)
    J = np.column_stack([J_S, -nM]) / sigma[:, None]
    res = (r - g) / sigma
    chi2 = float(res @ res)
    p = len(E)
    dof = len(y) - p - 3
    C9, inflation = gauss_newton_cov(J, chi2, dof)
    # dM/dS_k = -M E_k M.
    G = np.zeros((12, p + 3))
    G[:9, :p] = -np.einsum("ij,kjl,lm->kim", M, E, M).reshape(p, 9).T
    G[9:, p:] = np.eye(3)
    return {
        "cov12": G @ C9 @ G.T,
        "rms_residual": float(np.sqrt(np.mean((r - g) ** 2))),
        "chi2": chi2, "dof": dof, "inflation": inflation,
    }

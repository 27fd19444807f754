"""A fitted forward model and its linearisation: what the solver hands to the diagnosis.

``fit(model)`` runs Levenberg-Marquardt on the model's whitened residuals (locals
and globals together, linear in the recording's length: ``solvers/blocktri.py``)
and returns a ``Linearised``: the whitened residual vector at the optimum, the
Jacobian with named column blocks (globals) and the locals' sparse block, the
rows' metadata, the exact leverage of every row, the globals' covariance with
every nuisance marginalised, and chi-square per block with its effective degrees
of freedom. The diagnosis, the verdict and the uncertainty report all read this
one object.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..solvers.blocktri import Bordered, solve_least_squares
from .forward import BLOCKS, Globals, JointModel, Rows


@dataclass
class Linearised:
    """``r`` (N,) whitened residual; ``J_g`` (N, P_g) and ``J_l`` (N, P_l) CSR its Jacobian;
    ``x_g``/``x_l`` the solution; ``rows`` metadata; ``leverage`` (N,); ``cov_g`` (P_g, P_g)."""

    model: JointModel
    x_g: np.ndarray
    x_l: np.ndarray
    r: np.ndarray
    J_g: np.ndarray
    J_l: sp.csr_matrix
    iterations: int
    converged: bool
    leverage: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    _system: Bordered | None = field(repr=False, default=None)
    _gravity: tuple | None = field(repr=False, default=None)

    @property
    def system(self) -> Bordered:
        """The normal equations at the solution (built on first use)."""
        if self.J_g is None:
            raise ValueError("no J_g kept: a fit of the nuisances alone without leverages (fit's docstring), "
                             "or forget_jacobians")
        if self._system is None:
            self._system = Bordered(self.J_g, self.J_l, self.model.stages.offsets)
        return self._system

    def gravity(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Gravity's direction (model frame) at the rests (n, 3) and at the motions'
        accelerometer samples (k, 3; None without them), at the solution: one residual-only
        evaluation, kept for the candidates' signals and the per-sample table."""
        if self._gravity is None:
            sig = self.model.residuals(self.x_g, self.x_l, signals=True, jacobian=False)[3]
            self._gravity = (sig["gravity_rest"], sig.get("gravity_motion"))
        return self._gravity

    def forget_jacobians(self) -> None:
        """Drop the Jacobians and the normal equations (the largest arrays of a long recording)
        once nothing needs them: the residuals, leverages and solution stay."""
        self.J_g = self.J_l = self._system = None

    @property
    def rows(self) -> Rows:
        return self.model.rows

    @property
    def globals(self) -> Globals:
        return self.model.glob

    @property
    def chi2(self) -> float:
        return float(self.r @ self.r)

    @property
    def dof(self) -> int:
        return len(self.r) - self.model.glob.size - self.model.stages.size

    def cov_g(self) -> np.ndarray:
        """(P_g, P_g) covariance of the globals, nuisances marginalised (not inflated)."""
        return self.system.global_covariance()

    def blocks(self) -> dict[str, dict[str, Any]]:
        """chi2, rows, effective dof (rows minus their leverage) and RMS per block."""
        out = {}
        for i, name in enumerate(BLOCKS):
            sel = self.rows.block == i
            rows = int(sel.sum())
            if not rows:
                continue
            chi2 = float(self.r[sel] @ self.r[sel])
            dof = float(rows - self.leverage[sel].sum())
            out[name] = {"chi2": chi2, "rows": rows, "dof": dof,
                         "chi2_per_dof": chi2 / dof if dof > 0 else None,
                         "rms": float(np.sqrt(chi2 / rows))}
        return out

    def project(self, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(I - P) C`` for columns ``C`` (N, k) (P the projection onto the Jacobian's span: what
        the calibration and the nuisances can already fit) and ``z_g`` (P_g, k), the globals'
        shift per unit of each column. One block-tridiagonal solve for all k columns; the
        result is formed in place (no N x k temporaries beyond one product)."""
        C = np.asarray(C, float)
        z_g, z_l = self.system.solve(self.J_g.T @ C, np.asarray(self.J_l.T @ C))
        out = C.copy()
        out -= self.J_g @ z_g
        out -= self.J_l @ z_l
        return out, z_g

    def variance_of(self, a_g: np.ndarray, a_l: np.ndarray) -> np.ndarray:
        """(k, k) covariance of linear combinations ``a_g x_g + a_l x_l`` (``a_g`` (k, P_g),
        ``a_l`` (k, P_l)) under the fit's inverse normal matrix."""
        z_g, z_l = self.system.solve(a_g.T, a_l.T)
        return a_g @ z_g + a_l @ z_l


def fit(model: JointModel, max_iter: int = 30, x_g: np.ndarray | None = None,
        x_l: np.ndarray | None = None, fixed_globals: bool = False, tol: float = 1e-10,
        leverage: bool = True) -> Linearised:
    """Fit ``model`` from its start (or ``x_g``/``x_l``); ``fixed_globals``: only the nuisances
    move (the model's prediction of a given calibration), the leverage still counts the globals;
    ``leverage=False`` skips the rows' leverages (a fit only its solution is wanted from); with
    ``fixed_globals`` too, the globals' Jacobian is never formed (``J_g`` None), nor the locals'
    at the last point when ``max_iter`` ends the fit (``J_l`` None then)."""
    x_g = model.x_g0.copy() if x_g is None else np.asarray(x_g, float)
    x_l = model.x_l0.copy() if x_l is None else np.asarray(x_l, float)
    offsets = model.stages.offsets
    local_only = fixed_globals and not leverage
    residuals = (lambda g, l, out=None: model.residuals(g, l, with_globals=False, out=out)) if local_only \
        else model.residuals
    x_g, x_l, r, J_g, J_l, it, ok = solve_least_squares(
        residuals, x_g, x_l, offsets, max_iter=max_iter, tol=tol, fixed_globals=fixed_globals,
        residual=lambda g, l: model.residuals(g, l, jacobian=False)[0], final_jacobian=not local_only)
    if local_only:
        J_g = None
    lin = Linearised(model, x_g, x_l, r, J_g, J_l, it, ok)
    lin.leverage = lin.system.leverage() if leverage else None
    return lin

"""Sparse least squares in time order: nuisances in a block-tridiagonal chain, a few global unknowns.

The joint calibration problem (``imupipe.diagnosis.forward``) has this shape: the
unknowns are a handful of *global* parameters (scale, bias, ...) and many *local*
nuisances grouped in *stages* along time (a rest's gravity direction, the bias
random walk at its boundaries, the attitude error of the motion that follows),
and every residual row touches the globals and the locals of at most two
consecutive stages. The normal matrix is then block-tridiagonal in the locals,
bordered by a dense global block::

    A = [[A_ll, A_lg],      A_ll block-tridiagonal (stage blocks D_i, sub-diagonal E_i)
         [A_gl, A_gg]]      A_gg (p, p) dense, p small

Everything here is linear in the number of stages: a block Cholesky of ``A_ll``
(``BlockTridiagonal``), the Schur complement onto the globals (``Bordered``),
the selected inverse (the blocks of ``A_ll^-1`` on its own pattern, by the
block Takahashi recursion) and from it the exact leverage of every row
(``diag(J A^-1 J^T)``), which the residual map needs for honest degrees of
freedom.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_solve, cholesky, solve_triangular
from scipy.linalg.lapack import dpotrf, dtrtrs

from ..errors import SolverError

ROW_CHUNK = 1 << 16  # rows of a Jacobian taken at once where a product would copy it whole (memory)
# rows of equal length worth forming J^T J from dense blocks: a per-sample model's, not the
# joint refinement's (its sums stay scipy's: its weakly determined temperature coefficients
# would move by 1e-8 with the rounding)
MIN_STRETCH = ROW_CHUNK
HOPEFUL = 1e-6  # a step that cut the cost by more (relative) leaves its successor likely taken
# damping below which a step's predicted decrease is the Gauss-Newton step's (to 0.1 %)
NEAR_GAUSS_NEWTON = 1e-3


def finite(a: np.ndarray) -> np.ndarray:
    """``a``, checked as scipy.linalg checks what it hands LAPACK."""
    if not np.isfinite(a).all():
        raise ValueError("array must not contain infs or NaNs")
    return a


def _lower_solve(C: np.ndarray, b: np.ndarray, trans: int = 0) -> np.ndarray:
    """``solve_triangular(C, b, lower=True, trans=trans)`` for a ``dpotrf`` factor ``C`` (Fortran
    order, as scipy then calls LAPACK: the same arithmetic), called on LAPACK directly: the
    stages' blocks are small, and scipy's checks cost 5x the solve itself."""
    x, info = dtrtrs(C, finite(b), lower=1, trans=trans)
    if info:
        raise np.linalg.LinAlgError(f"singular matrix: resolution failed at diagonal {info - 1}")
    return x


@dataclass
class BlockTridiagonal:
    """An SPD matrix with stage blocks ``diag[i]`` (n_i, n_i) and ``lower[i]`` = block
    (i+1, i) of shape (n_{i+1}, n_i). ``offsets`` (len(diag) + 1,) are the stages' first rows.
    Factored (on first use), it keeps the factors alone: ``diag`` and ``lower`` become None."""

    diag: list[np.ndarray]
    lower: list[np.ndarray]

    def __post_init__(self) -> None:
        sizes = [d.shape[0] for d in self.diag]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self._C: list[np.ndarray] | None = None
        self._G: list[np.ndarray] | None = None

    @property
    def size(self) -> int:
        return int(self.offsets[-1])

    @classmethod
    def from_sparse(cls, A: sp.spmatrix, offsets: np.ndarray) -> BlockTridiagonal:
        """The stage blocks of a sparse symmetric ``A`` (entries outside them must be zero):
        every entry is written into its block at once (slicing block by block costs 20x more)."""
        A = sp.csr_matrix(A)
        if not A.has_canonical_format:
            A = A.copy()
            A.sum_duplicates()
        o = np.asarray(offsets, dtype=np.int64)
        n = np.diff(o)
        rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
        stage = np.repeat(np.arange(len(n)), n)  # of each row and column
        s_r, s_c = stage[rows], stage[A.indices]
        base_d = np.r_[0, np.cumsum(n * n)]
        base_l = np.r_[0, np.cumsum(n[1:] * n[:-1])]
        flat_d, flat_l = np.zeros(base_d[-1]), np.zeros(base_l[-1])
        m = s_r == s_c
        s = s_r[m]
        flat_d[base_d[s] + (rows[m] - o[s]) * n[s] + A.indices[m] - o[s]] = A.data[m]
        m = s_r == s_c + 1  # block (s + 1, s), shape (n[s + 1], n[s])
        s = s_c[m]
        flat_l[base_l[s] + (rows[m] - o[s + 1]) * n[s] + A.indices[m] - o[s]] = A.data[m]
        diag = [flat_d[base_d[i]:base_d[i + 1]].reshape(n[i], n[i]) for i in range(len(n))]
        lower = [flat_l[base_l[i]:base_l[i + 1]].reshape(n[i + 1], n[i]) for i in range(len(n) - 1)]
        return cls(diag, lower)

    # ------------------------------------------------------------------ factor
    def factor(self) -> None:
        """Block Cholesky ``A = L L^T``: ``C_i`` lower-triangular diagonal blocks, ``G_i`` the
        sub-diagonal blocks of ``L``. Raises ``SolverError`` when ``A`` is not positive definite.
        The factors replace ``A``'s blocks, each let go once used (a long recording's system is
        then held once, not twice)."""
        diag, lower = self.diag, self.lower
        self.diag = self.lower = None
        n = len(diag)
        C, G = [], []
        S = diag[0]
        for i in range(n):
            diag[i] = None
            if S.shape[0]:
                Ci, info = dpotrf(finite(S), lower=1, clean=1)
                if info:
                    raise SolverError("the nuisance parameters are not determined by the data "
                                      f"(stage {i} of {n})")
            else:
                Ci = S
            C.append(Ci)
            if i + 1 < n:
                E, lower[i] = lower[i], None
                Gi = _lower_solve(Ci, E.T).T if Ci.shape[0] else E[:, :0]
                G.append(Gi)
                S = diag[i + 1] - Gi @ Gi.T
        self._C, self._G = C, G

    def _factors(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        if self._C is None:
            self.factor()
        return self._C, self._G  # type: ignore[return-value]

    def logdet(self) -> float:
        C, _ = self._factors()
        return float(sum(2 * np.log(np.diag(c)).sum() for c in C))

    # ------------------------------------------------------------------ solve
    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` for ``b`` (N,) or (N, k)."""
        C, G = self._factors()
        o = self.offsets
        vec = b.ndim == 1
        y = np.array(b, dtype=float).reshape(len(b), -1)
        for i, Ci in enumerate(C):  # forward: L y = b
            if i:
                y[o[i]:o[i + 1]] -= G[i - 1] @ y[o[i - 1]:o[i]]
            if Ci.shape[0]:
                y[o[i]:o[i + 1]] = _lower_solve(Ci, y[o[i]:o[i + 1]])
        for i in range(len(C) - 1, -1, -1):  # backward: L^T x = y
            if i + 1 < len(C):
                y[o[i]:o[i + 1]] -= G[i].T @ y[o[i + 1]:o[i + 2]]
            if C[i].shape[0]:
                y[o[i]:o[i + 1]] = _lower_solve(C[i], y[o[i]:o[i + 1]], trans=1)
        return y[:, 0] if vec else y

    # ------------------------------------------------------------------ selected inverse
    def selected_inverse(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The blocks of ``Z = A^-1`` on the pattern of ``A``: ``Z_ii`` and ``Z_{i+1,i}``.

        From ``L^T Z = L^-1`` (block Takahashi recursion, last stage first):
        ``Z_{i,i+1} = -C_i^-T G_i^T Z_{i+1,i+1}`` and
        ``Z_ii = C_i^-T (C_i^-1 - G_i^T Z_{i+1,i})``.
        """
        C, G = self._factors()
        n = len(C)
        Zd: list[np.ndarray] = [np.zeros((0, 0))] * n
        Zl: list[np.ndarray] = [np.zeros((0, 0))] * max(n - 1, 0)
        for i in range(n - 1, -1, -1):
            Ci = C[i]
            k = Ci.shape[0]
            Cinv = _lower_solve(Ci, np.eye(k)) if k else np.zeros((0, 0))
            if i == n - 1:
                Zd[i] = Cinv.T @ Cinv
                continue
            Zu = -_lower_solve(Ci, G[i].T @ Zd[i + 1], trans=1) if k else \
                np.zeros((0, Zd[i + 1].shape[0]))  # Z_{i,i+1}
            Zl[i] = Zu.T
            Zd[i] = _lower_solve(Ci, Cinv - G[i].T @ Zu.T, trans=1) if k else Cinv
            Zd[i] = 0.5 * (Zd[i] + Zd[i].T)
        return Zd, Zl

    def row_forms(self, J: sp.csr_matrix, chunk: int = 2048) -> np.ndarray:
        """(N,) ``diag(J A^-1 J^T)`` for a sparse ``J`` whose rows touch two consecutive stages
        at most, from the selected inverse: per row, the quadratic form of its few entries with
        the inverse's block on their columns. Consecutive rows on the same columns (the samples
        of one knot interval) share that block; nothing of size N x q is formed, and the rows
        are taken ``chunk`` at a time (each row's form alone: the same bits for any chunk; a
        chunk's (rows, width, width) blocks are a few MiB, where 8192 rows made the leverage
        the refine stage's peak)."""
        J = sp.csr_matrix(J)
        if not J.has_canonical_format:
            J = J.copy()
            J.sum_duplicates()
        N = J.shape[0]
        if not N or not J.nnz:
            return np.zeros(N)
        Zd, Zl = self.selected_inverse()
        inverse = (np.concatenate([z.ravel() for z in Zd]) if Zd else np.zeros(0),
                   np.concatenate([z.ravel() for z in Zl] + [np.zeros(0)]),
                   np.r_[0, np.cumsum([z.size for z in Zd])][:-1].astype(np.int64),
                   np.r_[0, np.cumsum([z.size for z in Zl])].astype(np.int64))
        width = int(np.diff(J.indptr).max())
        return np.concatenate([self._row_forms(J[a:a + chunk], width, inverse) for a in range(0, N, chunk)])

    def _row_forms(self, J: sp.csr_matrix, width: int, inverse: tuple) -> np.ndarray:
        """``row_forms`` of the rows ``J``, at most ``width`` entries each, given the selected
        inverse's blocks flattened (``inverse``: diagonal and lower blocks, and where each starts)."""
        flat_d, flat_l, base_d, base_l = inverse
        o = self.offsets
        n = np.diff(o)
        N = J.shape[0]
        counts = np.diff(J.indptr)
        row = np.repeat(np.arange(N), counts)
        pos = np.arange(J.nnz) - J.indptr[row]
        cols = np.full((N, width), -1, np.int64)
        vals = np.zeros((N, width))
        cols[row, pos] = J.indices
        vals[row, pos] = J.data
        del row, pos
        start = np.r_[True, np.any(cols[1:] != cols[:-1], axis=1)]
        run = np.cumsum(start) - 1
        c = cols[start]  # (R, width) the columns of each run of rows
        # the inverse's entries on each run's column pairs, from the stage blocks
        stage = np.searchsorted(o, np.maximum(c, 0), "right") - 1
        within = np.maximum(c, 0) - o[stage]
        s1, s2 = stage[:, :, None], stage[:, None, :]
        w1, w2 = within[:, :, None], within[:, None, :]
        real = (c[:, :, None] >= 0) & (c[:, None, :] >= 0)
        Zr = np.zeros((len(c), width, width))
        m = real & (s1 == s2)
        Zr[m] = flat_d[(base_d[s1] + w1 * n[s1] + w2)[m]]
        m = real & (s1 == s2 + 1)  # block (s2 + 1, s2) = Zl[s2], shape (n[s2 + 1], n[s2])
        Zr[m] = flat_l[(base_l[np.maximum(s2, 0)] + w1 * n[np.maximum(s2, 0)] + w2)[m]]
        m = real & (s2 == s1 + 1)  # its transpose
        Zr[m] = flat_l[(base_l[np.maximum(s1, 0)] + w2 * n[np.maximum(s1, 0)] + w1)[m]]
        v = vals[:, :, None]
        return (np.swapaxes(v, 1, 2) @ (Zr[run] @ v))[:, 0, 0]

    def selected_sparse(self) -> sp.csr_matrix:
        """``selected_inverse`` as a sparse symmetric (N, N) matrix (zero outside the pattern)."""
        Zd, Zl = self.selected_inverse()
        o = self.offsets
        rows, cols, vals = [], [], []

        def put(block: np.ndarray, r0: int, c0: int) -> None:
            if block.size:
                r, c = np.indices(block.shape)
                rows.append((r + r0).ravel())
                cols.append((c + c0).ravel())
                vals.append(block.ravel())

        for i, z in enumerate(Zd):
            put(z, o[i], o[i])
        for i, z in enumerate(Zl):
            put(z, o[i + 1], o[i])
            put(z.T, o[i], o[i + 1])
        if not rows:
            return sp.csr_matrix((self.size, self.size))
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(self.size, self.size))


def _gram(J: sp.csr_matrix, chunk: int = ROW_CHUNK) -> sp.csr_matrix:
    """``J^T J``. Consecutive rows with the same columns (a motion's samples between two knots)
    add one small dense block each: over the longest stretch of rows holding the same number of
    entries, each run's block is a dense product of its rows (4x faster than the sparse product,
    which visits every pair of entries one at a time); the other rows go through scipy, by
    chunks of rows (the product transposes its operand: a chunk's copy is small)."""
    n = np.diff(J.indptr)
    if not len(n):
        return _sparse_gram(J, chunk)
    bounds = np.flatnonzero(np.r_[True, n[1:] != n[:-1], True])  # stretches of equally long rows
    i = int(np.argmax(np.diff(bounds)))
    a, b, K = bounds[i], bounds[i + 1], int(n[bounds[i]])
    if K == 0 or b - a < MIN_STRETCH:
        return _sparse_gram(J, chunk)
    cols = J.indices[J.indptr[a]:J.indptr[b]].reshape(-1, K)  # views: each row's columns and values
    vals = J.data[J.indptr[a]:J.indptr[b]].reshape(-1, K)
    starts = np.flatnonzero(np.r_[True, np.any(cols[1:] != cols[:-1], axis=1)])
    if len(starts) * K > len(cols):  # short runs: their blocks would outweigh the rows themselves
        return _sparse_gram(J, chunk)
    length = np.diff(np.r_[starts, len(cols)])
    blocks = np.empty((len(starts), K, K))
    first = 0
    while first < len(starts):  # runs of about ``chunk`` rows at a time, by their length
        last = max(int(np.searchsorted(starts, starts[first] + chunk)), first + 1)
        for size in np.unique(length[first:last]):
            sel = first + np.flatnonzero(length[first:last] == size)
            X = vals[starts[sel][:, None] + np.arange(size)]  # (runs, size, K)
            blocks[sel] = np.matmul(X.transpose(0, 2, 1), X)
        first = last
    pattern = cols[starts]
    dense = sp.csr_matrix((blocks.ravel(), (np.repeat(pattern, K, axis=1).ravel(), np.tile(pattern, K).ravel())),
                          shape=(J.shape[1], J.shape[1]))
    rest = sp.vstack([J[:a], J[b:]], format="csr")
    return (dense + _sparse_gram(rest, chunk)).tocsr()


def _sparse_gram(J: sp.csr_matrix, chunk: int) -> sp.csr_matrix:
    A = sp.csr_matrix((J.shape[1], J.shape[1]))
    for a in range(0, J.shape[0], chunk):
        Jc = J[a:a + chunk]
        A = A + (Jc.T @ Jc)
    return A.tocsr()


@dataclass
class Bordered:
    """The normal equations of ``r(x_g, x_l)`` with Jacobians ``J_g`` (N, p) dense and ``J_l``
    (N, q) sparse whose locals form the block-tridiagonal stages ``offsets``.

    ``damping`` adds ``lambda diag(A)`` (Levenberg-Marquardt); 0 gives the plain normal
    equations whose inverse is the covariance.
    """

    J_g: np.ndarray
    J_l: sp.csr_matrix
    offsets: np.ndarray
    damping: float = 0.0

    def __post_init__(self) -> None:
        J_l = self.J_l
        A_ll = _gram(J_l)
        self.A_lg = np.asarray(J_l.T @ self.J_g)
        self.A_gg = self.J_g.T @ self.J_g
        if self.damping:
            A_ll = A_ll + sp.diags(self.damping * A_ll.diagonal())
            self.A_gg = self.A_gg + np.diag(self.damping * np.diag(self.A_gg))
        self.blocks = BlockTridiagonal.from_sparse(A_ll, self.offsets)
        self.X = self.blocks.solve(self.A_lg) if self.A_lg.size else np.zeros((self.blocks.size, 0))
        S = self.A_gg - self.A_lg.T @ self.X
        self.S = 0.5 * (S + S.T)
        try:
            self._S_chol = cholesky(self.S, lower=True) if len(self.S) else self.S
        except np.linalg.LinAlgError:
            raise SolverError("the global parameters are not determined by the data") from None

    def solve(self, g_g: np.ndarray, g_l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(x_g, x_l)`` solving ``A [x_g; x_l] = [g_g; g_l]``."""
        y = self.blocks.solve(g_l)  # a fresh array: x_l is formed in it (k columns of P_l each)
        x_g = cho_solve((self._S_chol, True), g_g - self.A_lg.T @ y) if len(self.S) else np.zeros(0)
        y -= self.X @ x_g
        return x_g, y

    def step(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Gauss-Newton (or damped) step ``-A^-1 J^T r`` as ``(dx_g, dx_l)``."""
        x_g, x_l = self.solve(-(self.J_g.T @ r), -np.asarray(self.J_l.T @ r))
        return x_g, x_l

    def solver_only(self) -> Bordered:
        """Itself without its Jacobians (``solve`` and ``global_covariance`` need only the
        factors; ``step`` and ``leverage`` then cannot run): a system built on a scaled copy of
        J_l keeps that copy otherwise."""
        self.J_g = self.J_l = None
        return self

    def global_covariance(self) -> np.ndarray:
        """(p, p) ``(A^-1)_gg = S^-1``: the globals' covariance with every local marginalised."""
        return cho_solve((self._S_chol, True), np.eye(len(self.S))) if len(self.S) else self.S

    def leverage(self, chunk: int = ROW_CHUNK) -> np.ndarray:
        """(N,) ``diag(J A^-1 J^T)``, exact: ``a^T A_ll^-1 a + (g - X^T a)^T S^-1 (g - X^T a)``
        per row, the first term from the selected inverse (rows touch two stages at most)."""
        J_l = self.J_l
        out = self.blocks.row_forms(J_l)
        if not len(self.S):
            return out
        for a in range(0, len(out), chunk):  # G - J_l X, a chunk of rows at a time, is as wide as J_g
            Gt = self.J_g[a:a + chunk] - np.asarray(J_l[a:a + chunk] @ self.X)
            W = solve_triangular(self._S_chol, Gt.T, lower=True)
            out[a:a + chunk] += np.einsum("ij,ij->j", W, W)
        return out


def solve_least_squares(residuals, x_g: np.ndarray, x_l: np.ndarray, offsets: np.ndarray,
                        max_iter: int = 30, tol: float = 1e-10, fixed_globals: bool = False, residual=None,
                        final_jacobian: bool = True):
    """Levenberg-Marquardt on ``residuals(x_g, x_l) -> (r, J_g, J_l)``.

    Returns ``(x_g, x_l, r, J_g, J_l, iterations, converged)`` at the optimum. Converged when
    the relative decrease of the cost falls below ``tol``, or when a step damped by at most
    ``NEAR_GAUSS_NEWTON`` is refused although the linearisation predicts it to gain less than
    ``tol``: at the optimum rounding decides, and each further trial would cost a residual and
    a factorisation to be refused again; then one undamped Gauss-Newton step polishes the
    solution (the damping would otherwise leave it ~1e-8 short), with the last Jacobians formed:
    when the converging step was judged by its residual alone, the point before's (at the
    optimum they barely move; one Jacobian fewer: the map's fit moves by less than another
    BLAS kernel's rounding moves it, ``bench/residual_identity.py``). ``fixed_globals``:
    only the locals move; ``J_g`` is still returned at the optimum. ``residual(x_g, x_l) -> r``
    (optional): the Jacobians are then formed over the old ones
    (``residuals(x_g, x_l, out=(J_g, J_l))``: one set in memory, and no fresh pages for the
    kernel to clear at every step). After a step that cut the cost by more than ``HOPEFUL``
    of it, the next trial point is expected to be taken too: its Jacobians are formed with its
    residual (and formed again at the old point when it is refused); otherwise, near the
    optimum where rounding decides, ``residual`` alone judges it. ``final_jacobian=False`` (with
    ``residual``): only the solution is wanted when ``max_iter`` ends the fit unconverged, so its
    last point's Jacobians are not formed (``J_g``, ``J_l`` None then); the path is the same.
    """
    def predicted_decrease(J_g, J_l, r, d_g, d_l) -> float:
        """The cost's decrease the linearisation predicts for the step: |r|^2 - |r + J d|^2."""
        Jd = np.asarray(J_l @ d_l) if fixed_globals else J_g @ d_g + J_l @ d_l
        return -float(2 * (r @ Jd) + Jd @ Jd)

    def step(J_g: np.ndarray, J_l: sp.csr_matrix, r: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
        d_g, d_l = Bordered(J_g[:, :0] if fixed_globals else J_g, J_l, offsets, damping=lam).step(r)
        return (np.zeros(len(x_g)) if fixed_globals else d_g), d_l

    def over(J_g: np.ndarray, J_l: sp.csr_matrix, g: np.ndarray, l: np.ndarray) -> tuple:
        """The residual and Jacobians at ``g``, ``l``, the Jacobians written over ``J_g``, ``J_l``."""
        return residuals(g, l, out=(J_g, J_l))

    def trial(g: np.ndarray, l: np.ndarray, hopeful: bool) -> tuple:
        """The residual at a trial point, with its Jacobians when ``hopeful`` (None otherwise)."""
        if residual is None:
            return residuals(g, l)
        return over(J_g, J_l, g, l) if hopeful else (residual(g, l), None, None)

    r, J_g, J_l = residuals(x_g, x_l)
    cost = float(r @ r)
    lam = 1e-6
    converged = stale = False
    hopeful = True  # the next trial point is expected to be taken (see the docstring)
    it = 0
    for it in range(1, max_iter + 1):
        last = it == max_iter and not final_jacobian and residual is not None
        d_g, d_l = step(J_g, J_l, r, lam)
        while True:
            cand_g, cand_l = x_g + d_g, x_l + d_l
            r2, J_g2, J_l2 = trial(cand_g, cand_l, hopeful and not last)
            cost2 = float(r2 @ r2)
            if np.isfinite(cost2) and cost2 <= cost:
                break
            if residual is not None and J_g2 is not None:  # written over: the current point's again
                _, J_g, J_l = over(J_g, J_l, x_g, x_l)
            del r2, J_g2, J_l2
            hopeful = False
            if lam <= NEAR_GAUSS_NEWTON and predicted_decrease(J_g, J_l, r, d_g, d_l) < tol * cost:
                converged = True  # refused by rounding
                break
            lam *= 10.0
            if lam > 1e8:
                return x_g, x_l, r, J_g, J_l, it, converged
            d_g, d_l = step(J_g, J_l, r, lam)
        if converged:
            break
        decrease = (cost - cost2) / max(cost, 1e-300)
        hopeful = decrease > HOPEFUL
        x_g, x_l, cost = cand_g, cand_l, cost2
        if last and decrease >= tol:  # the end, unconverged: no polishing step needs them
            return x_g, x_l, r2, None, None, it, converged
        if decrease < tol:
            converged = True
            stale = J_g2 is None  # the polishing step uses the Jacobians of the point before
            r = r2
            if not stale:
                J_g, J_l = J_g2, J_l2
            break
        if J_g2 is None:
            J_g2, J_l2 = over(J_g, J_l, x_g, x_l)[1:]
        r, J_g, J_l = r2, J_g2, J_l2
        lam = max(lam / 10.0, 1e-12)
    if converged:  # an undamped Gauss-Newton step lands on the optimum (quadratic convergence)
        d_g, d_l = step(J_g, J_l, r, 0.0)
        r2, J_g2, J_l2 = trial(x_g + d_g, x_l + d_l, hopeful)
        if np.isfinite(r2 @ r2) and float(r2 @ r2) <= cost:
            x_g, x_l, r = x_g + d_g, x_l + d_l, r2
            if J_g2 is None:
                J_g2, J_l2 = over(J_g, J_l, x_g, x_l)[1:]
            J_g, J_l = J_g2, J_l2
        elif residual is not None and (J_g2 is not None or stale):
            _, J_g, J_l = over(J_g, J_l, x_g, x_l)
    return x_g, x_l, r, J_g, J_l, it, converged

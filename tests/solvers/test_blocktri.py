"""Block-tridiagonal bordered least squares: solve, covariance and leverages against dense algebra."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.linalg import cholesky, solve_triangular

from imupipe.errors import SolverError
from imupipe.solvers.blocktri import BlockTridiagonal, Bordered, _gram, solve_least_squares


def _chain(rng, sizes, rows_per_stage=7, p=4):
    """A random J_g (N, p), J_l (N, q): each row touches stage i and i+1's locals."""
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    rows_g, trip = [], []
    r = 0
    for i in range(len(sizes)):
        for _ in range(rows_per_stage):
            cols = list(range(offsets[i], offsets[i + 1]))
            if i + 1 < len(sizes) and rng.random() < 0.5:
                cols += list(range(offsets[i + 1], offsets[i + 2]))
            for c in cols:
                trip.append((r, c, rng.normal()))
            rows_g.append(rng.normal(size=p))
            r += 1
    rr, cc, vv = zip(*trip, strict=True)
    J_l = sp.csr_matrix((vv, (rr, cc)), shape=(r, offsets[-1]))
    return np.array(rows_g), J_l, offsets


def test_block_tridiagonal_solve_and_selected_inverse_match_dense():
    rng = np.random.default_rng(0)
    J_g, J_l, offsets = _chain(rng, [2, 3, 0, 4, 2, 5])
    A = (J_l.T @ J_l).toarray() + np.eye(J_l.shape[1]) * 0.1
    bt = BlockTridiagonal.from_sparse(sp.csr_matrix(A), offsets)
    b = rng.normal(size=(len(A), 2))
    assert np.allclose(bt.solve(b), np.linalg.solve(A, b), rtol=1e-10, atol=1e-12)
    assert bt.diag is None and bt.lower is None  # factored: the factors alone are kept
    Z = bt.selected_sparse().toarray()
    Zd = np.linalg.inv(A)
    mask = Z != 0
    assert mask.sum() > 0
    assert np.allclose(Z[mask], Zd[mask], rtol=1e-9, atol=1e-12)
    assert np.isclose(bt.logdet(), np.linalg.slogdet(A)[1])


def test_blocks_and_factors_are_scipys_to_the_bit():
    """The blocks are written in at once and the factors come from LAPACK directly: the same bits
    as slicing block by block and scipy's cholesky / solve_triangular, duplicates summed first."""
    rng = np.random.default_rng(3)
    _, J_l, offsets = _chain(rng, [3, 0, 4, 2, 5])
    A = sp.csr_matrix(J_l.T @ J_l + sp.eye(J_l.shape[1]) * 0.1)
    rows = [np.r_[a, a] for a in np.split(np.arange(A.nnz), A.indptr[1:-1])]  # every entry in two halves
    twice = sp.csr_matrix((0.5 * A.data[np.concatenate(rows)], A.indices[np.concatenate(rows)],
                           np.r_[0, np.cumsum([len(r) for r in rows])]), shape=A.shape)
    assert not twice.has_canonical_format
    bt = BlockTridiagonal.from_sparse(twice, offsets)
    o, Ad = offsets, A.toarray()
    for i in range(len(o) - 1):
        assert np.array_equal(bt.diag[i], Ad[o[i]:o[i + 1], o[i]:o[i + 1]])
    for i in range(len(o) - 2):
        assert np.array_equal(bt.lower[i], Ad[o[i + 1]:o[i + 2], o[i]:o[i + 1]])
    D0, E0 = bt.diag[0].copy(), bt.lower[0].copy()
    bt.factor()
    C0 = cholesky(D0, lower=True)
    assert np.array_equal(bt._C[0], C0)
    assert np.array_equal(bt._G[0], solve_triangular(C0, E0.T, lower=True).T)
    with pytest.raises(SolverError, match="stage 0"):
        BlockTridiagonal([-np.eye(2)], []).factor()
    with pytest.raises(ValueError, match="NaN"):
        BlockTridiagonal([np.full((2, 2), np.nan)], []).factor()


def test_bordered_covariance_and_leverage_match_dense():
    rng = np.random.default_rng(1)
    J_g, J_l, offsets = _chain(rng, [2, 2, 3, 2, 2, 3, 2], rows_per_stage=9)
    J = np.hstack([J_g, J_l.toarray()])
    A = J.T @ J
    Ainv = np.linalg.inv(A)
    sys = Bordered(J_g, J_l, offsets)
    p = J_g.shape[1]
    assert np.allclose(sys.global_covariance(), Ainv[:p, :p], rtol=1e-9)
    h = sys.leverage()
    assert np.allclose(h, np.einsum("ij,jk,ik->i", J, Ainv, J), rtol=1e-9, atol=1e-12)
    assert np.isclose(h.sum(), J.shape[1])
    # a long recording's rows are taken in chunks: the same numbers as all at once
    assert np.allclose(sys.leverage(chunk=5), h, rtol=1e-12, atol=1e-15)
    assert np.allclose(sys.blocks.row_forms(J_l, chunk=3), sys.blocks.row_forms(J_l, chunk=len(J)), rtol=1e-12)
    assert abs(_gram(J_l, chunk=4) - (J_l.T @ J_l)).max() < 1e-12
    r = rng.normal(size=len(J))
    d_g, d_l = sys.step(r)
    assert np.allclose(np.concatenate([d_g, d_l]), -np.linalg.solve(A, J.T @ r), rtol=1e-9)
    # without its Jacobians it still solves (and keeps no reference to them)
    g_g, g_l = J_g.T @ r, J_l.T @ r
    want = sys.solve(g_g, g_l)
    lean = Bordered(J_g, J_l, offsets).solver_only()
    assert lean.J_g is None and lean.J_l is None
    for got, exp in zip(lean.solve(g_g, g_l), want, strict=True):
        assert np.array_equal(got, exp)
    assert np.array_equal(lean.global_covariance(), sys.global_covariance())


def test_levenberg_marquardt_solves_a_nonlinear_chain():
    """y_i = exp(a) * (z_i + z_{i+1}) + c t_i with locals z (chain) and globals (a, c)."""
    rng = np.random.default_rng(2)
    n = 40
    t = np.linspace(0, 1, n)
    a, c = 0.3, -1.2
    z = rng.normal(size=n + 1)
    y = np.exp(a) * (z[:-1] + z[1:]) + c * t + 1e-3 * rng.normal(size=n)
    # each stage i holds z_i; row i touches stages i and i+1; z also has a weak prior
    offsets = np.arange(n + 2)

    def residuals(xg, xl):
        r = np.concatenate([y - np.exp(xg[0]) * (xl[:-1] + xl[1:]) - xg[1] * t, (xl - z) * 1e-3])
        Jg = np.zeros((len(r), 2))
        Jg[:n, 0] = -np.exp(xg[0]) * (xl[:-1] + xl[1:])
        Jg[:n, 1] = -t
        rows = np.r_[np.arange(n), np.arange(n), n + np.arange(n + 1)]
        cols = np.r_[np.arange(n), np.arange(1, n + 1), np.arange(n + 1)]
        vals = np.r_[np.full(n, -np.exp(xg[0])), np.full(n, -np.exp(xg[0])), np.full(n + 1, 1e-3)]
        return r, Jg, sp.csr_matrix((vals, (rows, cols)), shape=(len(r), n + 1))

    xg, xl, r, *_ , converged = solve_least_squares(residuals, np.array([0.0, 0.0]), z + 0.1, offsets)
    assert converged
    assert abs(xg[1] - c) < 0.05


def test_levenberg_marquardt_forming_jacobians_in_place_follows_the_same_path():
    """Rosenbrock's valley (globals) beside one linear local: the first steps overshoot and are
    refused. With ``residual`` given, a trial after a large decrease forms its Jacobians over
    the current ones (refused: formed again at the current point); the path and the optimum are
    the same as with fresh Jacobians at every trial."""
    offsets = np.array([0, 1])
    calls = {"in_place": 0, "residual": 0}

    def residuals(xg, xl, out=None):
        x, y = xg
        r = np.array([10 * (y - x * x), 1 - x, xl[0] - 1.0])
        J_g = np.zeros((3, 2)) if out is None else out[0]
        J_g[:] = [[-20 * x, 10], [-1, 0], [0, 0]]
        if out is not None:
            calls["in_place"] += 1
        return r, J_g, sp.csr_matrix(([1.0], ([2], [0])), shape=(3, 1))

    def residual(xg, xl):
        calls["residual"] += 1
        return residuals(xg, xl)[0]

    start = (np.array([-1.2, 1.0]), np.array([0.0]))
    fresh = solve_least_squares(residuals, *start, offsets, max_iter=200)
    in_place = solve_least_squares(residuals, *start, offsets, max_iter=200, residual=residual)
    assert calls["in_place"] > 0 and calls["residual"] > 0  # both kinds of trial were taken
    dense = lambda a: a.toarray() if sp.issparse(a) else a
    for a, b in zip(fresh[:5], in_place[:5], strict=True):
        np.testing.assert_array_equal(dense(a), dense(b))
    assert fresh[5:] == in_place[5:]
    np.testing.assert_allclose(in_place[0], [1.0, 1.0], atol=1e-6)


def test_levenberg_marquardt_without_the_final_jacobian_ends_at_the_same_point():
    """``final_jacobian=False``: a fit cut short by ``max_iter`` (the map's screening fit) whose
    solution alone is wanted takes the same steps, and its last point's Jacobians are never
    formed (fewer Jacobians; None returned). Converging, it polishes as before."""
    offsets = np.array([0, 1])
    full = {"n": 0}

    def residuals(xg, xl, out=None):
        full["n"] += 1
        x, y = xg
        r = np.array([10 * (y - x * x), 1 - x, xl[0] - 1.0])
        J_g = np.zeros((3, 2)) if out is None else out[0]
        J_g[:] = [[-20 * x, 10], [-1, 0], [0, 0]]
        return r, J_g, sp.csr_matrix(([1.0], ([2], [0])), shape=(3, 1))

    def residual(xg, xl):
        n = full["n"]
        r = residuals(xg, xl)[0]
        full["n"] = n  # Jacobians formed are counted, not residuals alone
        return r

    start = (np.array([-1.2, 1.0]), np.array([0.0]))
    runs, counts = {}, {}
    for final in (True, False):
        full["n"] = 0
        runs[final] = solve_least_squares(residuals, *start, offsets, max_iter=5, residual=residual,
                                          final_jacobian=final)
        counts[final] = full["n"]
    kept, cut = runs[True], runs[False]
    assert not cut[6] and cut[3] is None and cut[4] is None
    for a, b in zip(kept[:3], cut[:3], strict=True):
        np.testing.assert_array_equal(a, b)
    assert cut[5] == kept[5] == 5
    assert counts[False] < counts[True]
    converging = solve_least_squares(residuals, *start, offsets, max_iter=200, residual=residual,
                                     final_jacobian=False)
    assert converging[6] and converging[3] is not None
    np.testing.assert_allclose(converging[0], [1.0, 1.0], atol=1e-6)


def test_gram_from_runs_of_rows_alike_matches_the_sparse_product(monkeypatch):
    """A per-sample Jacobian's shape: a stretch of rows with K entries each, whose columns
    slide in runs of several lengths (knot intervals), between rows of other lengths touching
    the same columns. Dense blocks per run, by chunks of rows, give the sparse product's J^T J."""
    from imupipe.solvers import blocktri

    rng = np.random.default_rng(7)
    q, trip, row = 60, [], 0
    for _ in range(30):  # rows before the stretch, of 1 to 3 entries
        for c in rng.choice(q, int(rng.integers(1, 4)), replace=False):
            trip.append((row, c, rng.normal()))
        row += 1
    first = 0
    while first + 5 < q:  # the stretch: runs of 1 to 9 rows over 5 neighbouring columns
        for _ in range(int(rng.integers(1, 10))):
            trip += [(row, c, rng.normal()) for c in range(first, first + 5)]
            row += 1
        first += int(rng.integers(1, 3))
    trip += [(row, c, rng.normal()) for c in (0, 7, 59)]  # a row after it
    rr, cc, vv = zip(*trip, strict=True)
    J = sp.csr_matrix((vv, (rr, cc)), shape=(row + 1, q))
    monkeypatch.setattr(blocktri, "MIN_STRETCH", 8)
    want = (J.T @ J).toarray()
    for chunk in (1 << 16, 7):
        got = _gram(J, chunk=chunk)
        np.testing.assert_allclose(got.toarray(), want, rtol=1e-13, atol=1e-13)
        assert got.has_sorted_indices
    # a banded matrix's rows each start a run: K x K blocks per row would outweigh it, scipy's product
    banded = sp.diags([rng.normal(size=200) for _ in range(5)], range(5), shape=(200, 205), format="csr")
    sparse_calls = []
    monkeypatch.setattr(blocktri, "_sparse_gram", lambda J, chunk: sparse_calls.append(J.shape) or (J.T @ J).tocsr())
    np.testing.assert_allclose(_gram(banded).toarray(), (banded.T @ banded).toarray(), rtol=1e-13, atol=1e-13)
    assert sparse_calls == [banded.shape]


def test_levenberg_marquardt_ends_when_rounding_refuses_a_step_predicted_to_gain_nothing():
    """At the optimum a trial's cost is decided by rounding, here by a bump of 1e-12 off the
    start: a near Gauss-Newton step refused although the linearisation predicts it to gain less
    than ``tol`` ends the fit, converged, at the point it had (then the polishing step, refused
    too), instead of trying ever more damped steps until the damping gives up."""
    rng = np.random.default_rng(3)
    A, b = rng.normal(size=(20, 2)), rng.normal(size=20)
    best = np.linalg.lstsq(A, b, rcond=None)[0]
    start = best + 1e-9  # the linear model gains ~1e-18 of a cost ~10
    evaluations = {"n": 0}

    def residuals(xg, xl, out=None):
        evaluations["n"] += 1
        bump = 0.0 if np.array_equal(xg, start) else 1e-6
        r = np.r_[A @ xg - b, bump, xl[0] - 1.0]
        J_l = sp.csr_matrix(([1.0], ([21], [0])), shape=(22, 1))
        return r, np.vstack([A, np.zeros((2, 2))]), J_l

    xg, xl, *_, iterations, converged = solve_least_squares(
        residuals, start.copy(), np.array([1.0]), np.array([0, 1]), residual=lambda g, l: residuals(g, l)[0])
    assert converged and iterations == 1
    np.testing.assert_array_equal(xg, start)
    # the start, the refused step (with its Jacobians, and them again at the start) and the polish
    assert evaluations["n"] == 4


def test_levenberg_marquardt_polishes_from_the_last_jacobian_when_the_final_step_was_judged_by_its_residual():
    """A fit whose residual stays large at the optimum converges linearly: its last step, judged
    by the residual alone, gains less than ``tol``. The polishing Gauss-Newton step then uses the
    Jacobians of the point before (at the optimum they barely move) instead of forming them there:
    one Jacobian fewer, the same optimum as with fresh Jacobians at every trial, and the Jacobians
    returned are those of the point returned."""
    rng = np.random.default_rng(5)
    t = np.linspace(0, 2, 30)
    y = np.exp(0.7 * t) + 1.5 * rng.normal(size=30)
    formed = []

    def residuals(xg, xl, out=None):
        formed.append("J")
        e = np.exp(xg[0] * t)
        J_g = np.zeros((31, 2)) if out is None else out[0]
        J_g[:30, 0], J_g[:30, 1], J_g[30] = -t * e, -1.0, 0.0
        return np.r_[y - e - xg[1], xl[0] - 1.0], J_g, sp.csr_matrix(([1.0], ([30], [0])), shape=(31, 1))

    def residual(xg, xl):
        r = residuals(xg, xl)[0]
        formed[-1] = "r"
        return r

    start = (np.array([0.0, 0.0]), np.array([0.0]), np.array([0, 1]))
    fresh = solve_least_squares(residuals, *start, tol=1e-12)
    formed.clear()
    lean = solve_least_squares(residuals, *start, tol=1e-12, residual=residual)
    assert lean[6]
    # the converging step and the polishing step, both by their residual; then the Jacobians at the end
    assert "".join(formed).endswith("JrrJ")
    np.testing.assert_allclose(lean[0], fresh[0], rtol=1e-12)
    r, J_g, _ = residuals(lean[0], lean[1])
    np.testing.assert_array_equal(lean[2], r)
    np.testing.assert_array_equal(lean[3], J_g)

"""The residual engine's cheap paths give the numbers of the plain ones: the residual without its
Jacobian, the factored rate derivatives, J_l from its cached sparsity and from entries placed by
chunks, the fixed-globals fit's Jacobian, the Jacobians written over old ones, the reused
quadrature, the map with its Jacobians dropped early, its cells' bookkeeping, the fit's gravity
read once (issue 13: results identical within 1e-9)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from forward_synth import G, noise_free_imu, rests_from_truth, small_gimbal

from imupipe.diagnosis.attitude import Attitude, weighted
from imupipe.diagnosis.forward import JointModel, MotionAccel, Noise, Start
from imupipe.diagnosis.linearised import fit


def _model(out, truth, q):
    rests, turns = rests_from_truth(out, truth)
    cal = truth.calibration
    start = Start(np.linalg.inv(cal["accel"].M), cal["accel"].b0, cal["gyro"].M, cal["gyro"].b0,
                  cal["accel"].k, cal["gyro"].k)
    noise = Noise(np.eye(3) * 5e-3**2, np.eye(3) * 3.5e-4**2, np.full(3, q[0]), np.full(3, q[1]))
    acc = MotionAccel.select(out.t, out.raw["accel"], rests, turns)
    return JointModel(rests, turns, G, start, noise, fit_k=True, accel=acc, knot_s=0.25,
                      temperature=(out.t, out.temperature))


@pytest.fixture(scope="module")
def model():
    out, truth = small_gimbal(3, noise_free_imu(3))
    return _model(out, truth, q=(1e-9, 1e-10)), out


def _point(model, seed=0):
    rng = np.random.default_rng(seed)
    x_g = model.x_g0 + 1e-3 * rng.normal(size=model.glob.size) * np.abs(model.x_g0).clip(1e-2)
    return x_g, 1e-3 * rng.normal(size=model.stages.size)


def test_the_residual_alone_and_the_signals_equal_the_full_evaluation(model):
    m, _ = model
    x_g, x_l = _point(m)
    r, J_g, J_l, sig = m.residuals(x_g, x_l, signals=True)
    r0, none_g, none_l, sig0 = m.residuals(x_g, x_l, signals=True, jacobian=False)
    assert none_g is None and none_l is None
    assert np.array_equal(r, r0)
    for key, value in sig.items():
        assert np.array_equal(value, sig0[key]), key


def test_local_jacobian_from_the_cached_sparsity_equals_a_fresh_one(model):
    m, _ = model
    x_g, x_l = _point(m, 1)
    _, _, cached = m.residuals(x_g, x_l)  # the pattern is already cached by earlier calls
    m.forget_jacobian_places()  # as the map does after its last fit: the next one sorts again
    _, _, fresh = m.residuals(x_g, x_l)
    assert "_jl_pattern" in m.__dict__
    assert np.array_equal(cached.data, fresh.data)
    assert np.array_equal(cached.indptr, fresh.indptr) and np.array_equal(cached.indices, fresh.indices)
    want = fresh.copy()
    want.sort_indices()
    assert np.array_equal(want.indices, fresh.indices)  # CSR order: each row's columns ascending


def test_jacobians_written_over_earlier_ones_equal_fresh_ones(model):
    m, _ = model
    x_g, x_l = _point(m, 4)
    _, J_g, J_l = m.residuals(*_point(m, 5))  # an earlier step's, given up
    r, over_g, over_l = m.residuals(x_g, x_l, out=(J_g, J_l))
    r0, fresh_g, fresh_l = m.residuals(x_g, x_l)
    assert over_g is J_g and np.shares_memory(over_l.data, J_l.data)  # no fresh memory
    assert np.array_equal(r, r0) and np.array_equal(over_g, fresh_g) and (over_l != fresh_l).nnz == 0
    _, wrong_g, _ = m.residuals(x_g, x_l, with_globals=False, out=(fresh_g, fresh_l))  # other shape
    assert wrong_g.shape == (len(r), 0) and np.array_equal(fresh_g, over_g)


def test_factored_rate_derivatives_weigh_like_the_dense_ones(model):
    m, _ = model
    x_g, x_l = _point(m, 2)
    omega, D = m._rates(m.unpack(x_g), x_l)
    dense = D.dense()
    assert dense.shape == (len(m.motions), 3, 21)
    W = m.quad.A
    got, want = weighted(W, D), weighted(W, dense)
    assert np.allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
    att = Attitude.integrate(m.quad, omega)
    s1 = att.sensitivity(D, m.accel_points)
    s2 = Attitude.integrate(m.quad, omega).sensitivity(dense, m.accel_points)
    assert np.allclose(s1, s2, rtol=1e-12, atol=1e-12 * np.abs(s2).max())


def test_fixed_globals_fit_returns_the_jacobian_at_its_optimum(model):
    m, _ = model
    lin = fit(m, max_iter=3, fixed_globals=True)
    r, J_g, J_l = m.residuals(lin.x_g, lin.x_l)
    assert np.array_equal(lin.r, r) and np.array_equal(lin.J_g, J_g)
    assert (lin.J_l != J_l).nnz == 0
    assert np.array_equal(lin.x_g, m.x_g0)
    # the nuisances alone (no leverages): the globals' Jacobian is never formed, same solution
    alone = fit(m, max_iter=3, fixed_globals=True, leverage=False)
    assert alone.J_g is None
    assert np.allclose(alone.x_l, lin.x_l, rtol=1e-9, atol=1e-12 * np.abs(lin.x_l).max())
    r0, J_g0, J_l0 = m.residuals(lin.x_g, lin.x_l, with_globals=False)
    assert J_g0.shape == (len(r), 0) and np.array_equal(r0, r)
    assert np.allclose(J_l0.toarray(), J_l.toarray(), rtol=1e-12, atol=1e-12 * np.abs(J_l.data).max())


def test_the_fits_gravity_is_evaluated_once_for_the_signals_and_the_sample_table(model, monkeypatch):
    m, _ = model
    lin = fit(m, max_iter=2, fixed_globals=True, leverage=False)
    sig = m.residuals(lin.x_g, lin.x_l, signals=True, jacobian=False)[3]
    calls = []
    monkeypatch.setattr(m, "residuals", lambda *a, **k: calls.append(k) or JointModel.residuals(m, *a, **k))
    u_rest, u_motion = lin.gravity()
    assert lin.gravity()[1] is u_motion and len(calls) == 1
    assert np.array_equal(u_rest, sig["gravity_rest"]) and np.array_equal(u_motion, sig["gravity_motion"])


def test_a_model_reusing_anothers_quadrature_is_the_same_model(model):
    m, out = model
    acc = m.accel
    keep = acc.motion != acc.motion[0]  # one motion's samples dropped (as a carried motion is)
    sub = MotionAccel(acc.t[keep], acc.y[keep], acc.motion[keep])
    args = (m.rests, m.turns, m.g, m.start, m.noise)
    kw = dict(fit_k=m.fit_k, accel=sub, knot_s=0.25, temperature=(out.t, out.temperature))
    fresh, reused = JointModel(*args, **kw), JointModel(*args, **kw, like=m)
    assert reused.quad is m.quad
    assert (fresh.accel_points.W != reused.accel_points.W).nnz == 0
    assert np.array_equal(fresh.accel_points.h, reused.accel_points.h)
    x_g, x_l = fresh.x_g0, fresh.x_l0
    assert np.array_equal(fresh.residuals(x_g, x_l)[0], reused.residuals(x_g, x_l)[0])


@pytest.mark.parametrize("repeat", [False, True])
def test_local_jacobian_from_entries_is_scipys_csr(repeat):
    """Entries in any order (some given as where(), with or without their rows' span), repeats
    adding up: scipy's CSR of the same entries. Sources on disjoint rows, in any source order,
    are sorted in groups; sources whose rows overlap (the last two) sort together."""
    import scipy.sparse as sp

    rng = np.random.default_rng(7)
    N, Pl = 40, 9
    blocks = [(0, 10), (10, 22), (22, 30), (30, 40)]  # rows of each source; the last two overlap below
    trip, want_rows, want_cols, want_vals = [], [], [], []
    for b, (lo, hi) in enumerate(blocks):
        rows, cols = np.divmod(rng.permutation((hi - lo) * Pl)[:25], Pl)
        rows = rows + lo
        if b == 3:
            rows[:3] = [23, 25, 29]  # into the third source's rows (no repeat: its columns differ)
            cols[:3] = Pl - 1
        if repeat and b == 1:
            rows, cols = np.r_[rows, rows[3]], np.r_[cols, cols[3]]
        vals = rng.normal(size=len(rows))
        want_rows.append(rows), want_cols.append(cols), want_vals.append(vals)
        if b == 0:
            trip.append((lambda r=rows, c=cols: (r, c), None, vals))
        elif b == 2:
            trip.append((lambda r=rows, c=cols: (r, c), (lo, hi - 1), vals))
        else:
            trip.append((rows, cols, vals))
    assert not set(zip(want_rows[2], want_cols[2], strict=True)) & {(23, Pl - 1), (25, Pl - 1), (29, Pl - 1)}
    order = [3, 1, 0, 2]  # source order unlike the rows'
    trip = [trip[i] for i in order]
    rows, cols, vals = (np.concatenate([x[i] for i in order]) for x in (want_rows, want_cols, want_vals))
    want = sp.csr_matrix((vals, (rows, cols)), shape=(N, Pl))
    holder = type("Holder", (), {})()
    got = JointModel._local_jacobian(holder, trip, N, Pl)
    assert ("_jl_pattern" in holder.__dict__) != repeat
    if repeat:
        assert abs(got - want).max() < 1e-15
        return
    want.sum_duplicates()
    for a, b in ((got.indptr, want.indptr), (got.indices, want.indices), (got.data, want.data)):
        np.testing.assert_array_equal(a, b)
    assert all(t is None for t in trip)  # each source let go once placed


def test_the_map_without_its_jacobians_after_the_structure_cells_is_the_same_map():
    """The run's map stage forms the sample table only when first read and drops the fit's
    Jacobians once the structure cells are scored: the same document and table."""
    from imupipe.diagnosis.evaluate import evaluate
    from imupipe.diagnosis.residual_map import residual_map
    from imupipe.sim.sensor import default_imu

    out, truth = small_gimbal(4, default_imu(np.random.default_rng([4, 2])), n_rotations=12)
    rests, turns = rests_from_truth(out, truth)
    streams = {s: (out.t, out.raw[s]) for s in ("accel", "gyro")}
    cal = truth.calibration
    kept, lean = (evaluate(streams, rests, turns, cal["accel"], cal["gyro"], G) for _ in range(2))
    assert callable(lean.table)  # not formed yet
    doc = residual_map(kept)
    assert residual_map(lean, keep_jacobians=False) == doc
    assert lean.lin.J_g is None and lean.lin.J_l is None and kept.lin.J_g is not None
    for name in kept.samples.column_names:
        a, b = (_values(ev.samples.column(name)) for ev in (kept, lean))
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name  # NaN where no value
    assert not callable(lean.table)


def _values(column) -> np.ndarray:
    column = column.combine_chunks()
    if hasattr(column, "flatten"):  # fixed-size lists (x, y, z)
        column = column.flatten()
    return column.to_numpy(zero_copy_only=False)


def test_map_bookkeeping_without_hashing_or_sorting_every_row():
    """The residual map's cell bookkeeping: distinct values in a pass per value, pairs of
    (sensor, regime) with their rows, batch spreads by bincount (empty batches skipped) and
    windows of rows in time order, against ``np.unique`` and sorting."""
    from imupipe.diagnosis import residual_map as rm

    rng = np.random.default_rng(5)
    sensor = rng.choice(np.array(["gyro", "accel", "mag"]), 1000)
    regime = rng.choice(np.array(["static", "motion"]), 1000)
    axis = rng.integers(-1, 3, 1000)
    assert rm.levels(sensor) == list(np.unique(sensor)) and rm.levels(axis) == list(np.unique(axis))
    found = rm.pairs(sensor, regime)
    assert [k for k, _ in found] == sorted(set(zip(sensor.tolist(), regime.tolist(), strict=True)))
    for (s, g), idx in found:
        np.testing.assert_array_equal(idx, np.flatnonzero((sensor == s) & (regime == g)))

    t = np.sort(np.r_[rng.uniform(0, 40, 300), rng.uniform(100, 200, 300)])  # batches 8-19 empty
    r2, w = rng.chisquare(1, 600), rng.uniform(0.5, 1, 600)
    _, inv = np.unique(np.floor((t - t.min()) / rm.BATCH_S), return_inverse=True)
    S, W = np.bincount(inv, r2), np.bincount(inv, w)
    B, R = len(S), S.sum() / W.sum()
    assert rm._batch_sd(t, r2, w) == np.sqrt(B / (B - 1) * np.sum((S - R * W) ** 2)) / W.sum()

    order = rng.permutation(600)
    excess = r2 - w
    assert rm.windows(t[order], excess[order]) == rm.windows(t, excess)
    heavier = (t[300], t[-1]) if excess[300:].sum() > excess[:300].sum() else (t[0], t[299])
    assert rm.windows(t, excess, gap=30.0, keep=1) == [heavier]


def test_heldout_refit_with_rows_zeroed_in_place_is_the_weighted_copys(fitted):
    """A held-out refit forms its system on the Jacobian with the held-out rows zeroed in place
    and restored after: the same bits as on a weighted copy, and the Jacobian left as it was."""
    import scipy.sparse as sp

    from imupipe.diagnosis.select import _refit_predict
    from imupipe.solvers.blocktri import Bordered

    lin = fitted[-1]
    rng = np.random.default_rng(11)
    X = rng.normal(size=(len(lin.r), 2))
    J = np.hstack([lin.J_g, X])
    before = J.copy()
    train = np.ones(len(lin.r), bool)
    train[len(train) // 3: len(train) // 2] = False
    signal = X @ np.array([0.3, -0.2])
    got = _refit_predict(lin, J, 1, train, (signal,))
    np.testing.assert_array_equal(J, before)
    w = train.astype(float)
    Jw, Jl = before * w[:, None], (sp.diags(w) @ lin.J_l).tocsr()
    system = Bordered(Jw, Jl, lin.model.stages.offsets)
    for r, pair in zip((lin.r, signal), got, strict=True):
        g_g, g_l = -(Jw.T @ (r * w)), -np.asarray(Jl.T @ (r * w))
        y = system.blocks.solve(g_l)
        for P, value in zip((lin.J_g.shape[1] + 1, J.shape[1]), pair, strict=True):
            x_g = np.linalg.solve(system.S[:P, :P], g_g[:P] - system.A_lg[:, :P].T @ y)
            np.testing.assert_array_equal(value, r + before[:, :P] @ x_g + lin.J_l @ (y - system.X[:, :P] @ x_g))

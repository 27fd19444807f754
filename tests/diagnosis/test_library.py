"""The structure cells' statistics, accumulated over chunks of the library's columns, are the
dense formulas': the score of the projected columns (conditional on given terms) and its wild
bootstrap; the gyro signals carried into the motions match their exact column."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.diagnosis import library
from imupipe.diagnosis.select import Signals, time_blocks, wild_p


def _dense(lin, lib) -> np.ndarray:
    C = np.zeros((len(lin.r), len(lib.columns)))
    for rows, c in lib.chunks():
        C[rows] += c
    return C


def _cases(lin):
    rng = np.random.default_rng(1)
    r = lin.r + 0.01 * rng.standard_normal(len(lin.r))  # off the optimum: every term of the score counts
    return [(None, lin.r), (lin.project(rng.standard_normal((len(r), 2)))[0], r)]


def test_chunks_change_nothing(fitted, monkeypatch):
    lin = fitted[-1]
    for given, r in _cases(lin):
        whole = library.structure_cells(lin, given, r, bootstrap=True)
        monkeypatch.setattr(library, "CHUNK", 37)  # many chunks, the last one short
        chunked = library.structure_cells(lin, given, r, bootstrap=True)
        monkeypatch.undo()
        assert len(whole) == len(chunked) > 0
        for a, b in zip(whole, chunked):
            assert (a.sensor, a.regime, a.axes, a.dof, a.windows) == (b.sensor, b.regime, b.axes, b.dof, b.windows)
            assert b.chi2 == pytest.approx(a.chi2, rel=1e-9) and b.p_bootstrap == a.p_bootstrap


def test_rows_read_as_slices_change_no_bit(fitted, monkeypatch):
    """A chunk's rows, one ascending run, are read as a slice (J_g's view, J_l's stretch): every
    cell is the very number of the rows gathered one by one, the bootstrap's and the conditional
    test's included."""
    assert library._as_slice(np.arange(4, 9)) == slice(4, 9)
    for rows in (np.array([4, 5, 7]), np.array([5, 4, 6]), np.zeros(0, int)):
        assert library._as_slice(rows) is rows
    lin = fitted[-1]
    for given, r in _cases(lin):
        sliced = library.structure_cells(lin, given, r, bootstrap=True)
        monkeypatch.setattr(library, "_as_slice", lambda rows: rows)
        gathered = library.structure_cells(lin, given, r, bootstrap=True)
        monkeypatch.undo()
        assert [(c.sensor, c.regime, c.axes, c.chi2, c.dof, c.windows, c.p_bootstrap) for c in sliced] == \
            [(c.sensor, c.regime, c.axes, c.chi2, c.dof, c.windows, c.p_bootstrap) for c in gathered]


def test_a_fully_visible_cell_is_the_dense_score_test_and_its_bootstrap(fitted):
    lin = fitted[-1]
    libs = library.libraries(Signals(lin))
    checked = 0
    for given, r in _cases(lin):
        cells = library.structure_cells(lin, given, r, bootstrap=True)
        for lib in libs:
            C = _dense(lin, lib)
            rows = np.any(C != 0, axis=1)
            for cell in (c for c in cells if (c.sensor, c.regime) == (lib.sensor, lib.regime)):
                sel = [library.AXES[i] in cell.axes for i, *_ in lib.columns]
                X = lin.project(C[:, sel])[0]
                rr = r
                if given is not None:  # the given terms fitted too
                    X = X - given @ np.linalg.lstsq(given, X, rcond=None)[0]
                    rr = r - given @ np.linalg.lstsq(given, r, rcond=None)[0]
                if cell.dof != np.linalg.matrix_rank(X):  # some direction dropped as not visible
                    continue
                scale = max(1.0, float(rr[rows] @ rr[rows]) / float(np.sum(1 - lin.leverage[rows])))
                score = X.T @ rr
                assert cell.chi2 == pytest.approx(score @ np.linalg.solve(X.T @ X, score) / scale, rel=1e-6)
                assert cell.p_bootstrap == pytest.approx(wild_p(X, rr, time_blocks(lin)), abs=1e-12)
                checked += 1
    assert checked >= 4


def test_the_gyro_signals_reach_the_motions_as_the_exact_column_does(fitted):
    """Slow signals by their mean over each motion (within 5 %), the specific force exactly: a
    gravity-dependent term turns with the attitude inside a motion."""
    lin = fitted[-1]
    s = Signals(lin)
    motion = lin.rows.of("turn") | lin.rows.of("accel_motion")
    signals = {"dT^2": s.model.dT_gyro ** 2, **{f"f_{a}": s.f_gyro_motion[:, j] for j, a in enumerate(library.AXES)},
               **{f"|x_{a}|": np.abs(s.x_gyro_motion[:, j]) for j, a in enumerate(library.AXES)}}
    checked = set()
    for lib in (lb for lb in library.libraries(s) if lb.sensor == "gyro"):
        C = _dense(lin, lib)
        for c, (i, name, _, _) in enumerate(lib.columns):
            if name not in signals:
                continue
            dy = np.zeros((len(s.model.motions.t), 3, 1))
            dy[:, i, 0] = signals[name]
            exact = s.gyro_motion_column(dy)[:, 0]  # on the motions' rows, in order
            assert np.linalg.norm(exact) > 0
            tol = 0.05 if name == "dT^2" else 1e-12
            assert np.linalg.norm(C[motion, c] - exact) <= tol * np.linalg.norm(exact)
            checked.add((lib.regime, name))
    assert {name for _, name in checked} == set(signals) and ("motion", "|x_x|") in checked


def test_stability_selection_keeps_the_acting_signal_and_not_its_correlated_neighbours():
    """Block scores of six library columns, two of them (0, 3) acting; column 1 is 0.8
    correlated with column 0 (its marginal t is large too). The stable set is the acting two."""
    rng = np.random.default_rng(5)
    G, rows = 200, 50
    X = rng.normal(size=(G * rows, 6))
    X[:, 1] = 0.8 * X[:, 0] + 0.6 * X[:, 1]
    X /= np.linalg.norm(X, axis=0)
    truth = np.array([6.0, 0, 0, -5.0, 0, 0])
    r = X @ truth + rng.normal(size=len(X))
    g_b = (X * r[:, None]).reshape(G, rows, 6).sum(1)
    B = X.T @ X
    assert abs(g_b.sum(0)[1] / np.sqrt(B[1, 1])) > 3  # the neighbour alone looks significant
    stable = library._stable_terms(B, g_b.sum(0), g_b)
    assert sorted(j for j, *_ in stable) == [0, 3]
    for j, coefficient, t, share in stable:  # the coefficient is the term's (the residual's opposite)
        assert share >= library.STABLE_MIN and abs(-coefficient - truth[j]) < 3 and abs(t) > 4
    noise = (X * rng.normal(size=len(X))[:, None]).reshape(G, rows, 6).sum(1)
    assert library._stable_terms(B, noise.sum(0), noise) == []  # noise alone: nothing stable


def test_windows_from_the_chunks_grams_are_the_rows_windows():
    """A structure cell's windows come from each window's C'C summed in the one pass over the
    chunks: the same windows as ``residual_map.windows`` of every row's (C w)^2."""
    from types import SimpleNamespace

    from imupipe.diagnosis.residual_map import windows

    rng = np.random.default_rng(5)
    # rows out of time order across two parts (rest means, then motion samples), gaps between bursts
    t_rest = np.repeat(np.arange(40) * 10.0 + 4.0, 3)
    t_motion = np.repeat(np.sort(np.concatenate([s + rng.uniform(0, 3, 50) for s in np.arange(40) * 10.0])), 3)
    t = np.r_[t_rest, t_motion, np.nan]  # a row of no library: nothing reads it
    parts = [SimpleNamespace(rows=np.arange(len(t_rest)).reshape(-1, 3)),
             SimpleNamespace(rows=len(t_rest) + np.arange(len(t_motion)))]
    lib = SimpleNamespace(parts=parts, columns=[None] * 4)
    near = library._Windows(SimpleNamespace(rows=SimpleNamespace(t=t)), lib)
    C = rng.normal(size=(len(t) - 1, 4)) * np.where(t[:-1] > 200, 3.0, 1.0)[:, None]
    for a in range(0, len(C), 97):  # chunks that split samples and windows
        near.add(C[a:a + 97])
    w = rng.normal(size=4)
    cell = library.StructureCell("accel", ("x",), "motion", 1.0, 1.0, [])
    (placed,) = near.placed([(cell, w)])
    assert len(placed.windows) == 12 and placed.windows == windows(t[:-1], (C @ w) ** 2)

"""The forward model of a whole recording: exact on noise-free data, Jacobians by finite differences."""

from __future__ import annotations

import copy
import dataclasses
import itertools

import numpy as np
import pytest
from forward_synth import G, noise_free_imu, rests_from_truth, small_gimbal, small_sphere_rig

from imupipe.diagnosis import forward
from imupipe.diagnosis.attitude import RateDerivatives
from imupipe.diagnosis.forward import JointModel, MotionAccel, Noise, Start


def _model(out, truth, sampled=True, q=(0.0, 0.0), fit_k=True, knot_s=0.25):
    rests, turns = rests_from_truth(out, truth)
    cal = truth.calibration
    start = Start(np.linalg.inv(cal["accel"].M), cal["accel"].b0, cal["gyro"].M, cal["gyro"].b0,
                  cal["accel"].k, cal["gyro"].k)
    noise = Noise(np.eye(3) * 5e-3**2, np.eye(3) * 3.5e-4**2, np.full(3, q[0]), np.full(3, q[1]))
    acc = MotionAccel.select(out.t, out.raw["accel"], rests, turns) if sampled else None
    return JointModel(rests, turns, G, start, noise, fit_k=fit_k, accel=acc, knot_s=knot_s,
                      temperature=(out.t, out.temperature))


@pytest.fixture(scope="module")
def noise_free():
    return small_gimbal(3, noise_free_imu(3))


def test_noise_free_prediction_matches_the_simulator():
    """Every accelerometer sample, still or moving, predicted from the rests before it and the
    calibrated gyro. The sensor physics is the simulator's to 1e-9 relative (given the true
    specific force); the whole prediction, through the integrated attitude, to 1e-7: the
    simulator's turns start and stop between samples, where the rate's second derivative jumps,
    and no quadrature of sampled rates is better than O(dt^3) across such a kink (1e-8 rad)."""
    out, truth = small_sphere_rig(4, noise_free_imu(4))
    model = _model(out, truth)
    r, _, _, sig = model.residuals(model.x_g0, np.zeros(model.stages.size), signals=True)
    acc = model.accel
    assert len(acc.y) > 5000
    rest_err = np.linalg.norm(sig["pred_accel_rest"] - model.y_a, axis=1) / G
    assert rest_err.max() < 1e-9
    i = np.searchsorted(out.t, acc.t)
    f_true = out.inputs["accel"][i]
    physics = model.accel_prediction(model.unpack(model.x_g0), f_true, acc.t)
    assert np.max(np.linalg.norm(physics - acc.y, axis=1) / np.linalg.norm(acc.y, axis=1)) < 1e-9
    err = np.linalg.norm(sig["pred_accel_motion"] - acc.y, axis=1) / np.linalg.norm(acc.y, axis=1)
    assert err.max() < 1e-7
    assert np.abs(r).max() < 1e-2  # every whitened row at the truth: far below the noise (1)


@pytest.mark.parametrize("sampled,q", [(False, (0.0, 0.0)), (True, (1e-9, 1e-10))])
def test_jacobians_match_finite_differences(noise_free, sampled, q):
    out, truth = noise_free
    model = _model(out, truth, sampled=sampled, q=q)
    rng = np.random.default_rng(0)
    x_g = model.x_g0 + 1e-3 * rng.normal(size=model.glob.size) * np.abs(model.x_g0).clip(1e-2)
    x_l = 1e-3 * rng.normal(size=model.stages.size)
    r, J_g, J_l = model.residuals(x_g, x_l)
    J_l = J_l.toarray()
    local_cols = rng.choice(model.stages.size, size=min(60, model.stages.size), replace=False)
    for cols, J, which in ((range(model.glob.size), J_g, "g"), (local_cols, J_l, "l")):
        for c in cols:
            h = 1e-6 * max(1.0, abs((x_g if which == "g" else x_l)[c]))
            xp_g, xm_g, xp_l, xm_l = x_g.copy(), x_g.copy(), x_l.copy(), x_l.copy()
            if which == "g":
                xp_g[c] += h
                xm_g[c] -= h
            else:
                xp_l[c] += h
                xm_l[c] -= h
            fd = (model.residuals(xp_g, xp_l)[0] - model.residuals(xm_g, xm_l)[0]) / (2 * h)
            scale = max(1.0, np.abs(fd).max())
            assert np.abs(fd - J[:, c]).max() < 2e-5 * scale, (which, c, np.abs(fd - J[:, c]).max())


def test_the_motion_samples_derivatives_formed_in_chunks_are_the_same(noise_free, monkeypatch):
    out, truth = noise_free
    model = _model(out, truth, q=(1e-9, 1e-10))
    x_l = 1e-3 * np.random.default_rng(1).normal(size=model.stages.size)
    r, J_g, J_l = model.residuals(model.x_g0, x_l)
    assert len(model.accel.t) > 100
    monkeypatch.setattr(forward, "SAMPLE_CHUNK", 37)  # many chunks, the last one short
    fresh = _model(out, truth, q=(1e-9, 1e-10))  # no cached sparsity pattern
    r2, J_g2, J_l2 = fresh.residuals(fresh.x_g0, x_l)
    assert np.array_equal(r, r2)
    assert np.allclose(J_g, J_g2, rtol=1e-12, atol=1e-12)
    assert abs(J_l - J_l2).max() < 1e-12


def test_linear_time_fit_is_the_dense_least_squares_optimum(noise_free):
    """The block-tridiagonal Levenberg-Marquardt (``linearised.fit``) lands on the optimum a
    dense solver finds for the same whitened residuals, to 1e-9 relative: the speed changes
    nothing in the answer."""
    from scipy.optimize import least_squares

    from imupipe.diagnosis.linearised import fit

    out, truth = noise_free
    model = _model(out, truth, sampled=False, q=(1e-9, 1e-10))
    rng = np.random.default_rng(1)
    x_g0 = model.x_g0 + 1e-4 * rng.normal(size=model.glob.size)
    x_l0 = model.x_l0 + 1e-4 * rng.normal(size=model.stages.size)
    noisy = model.y_a + 5e-3 * rng.normal(size=model.y_a.shape)
    model.y_a = noisy  # a fit with a non-zero residual
    lin = fit(model, max_iter=50, x_g=x_g0, x_l=x_l0)
    P_g = model.glob.size

    def fun(x):
        return model.residuals(x[:P_g], x[P_g:])[0]

    def jac(x):
        _, J_g, J_l = model.residuals(x[:P_g], x[P_g:])
        return np.hstack([J_g, J_l.toarray()])

    x = least_squares(fun, np.r_[x_g0, x_l0], jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    for _ in range(5):  # dense Gauss-Newton to the optimum: SciPy 1.17.1's LM stopped 5e-8 short of it (xtol)
        x = x - np.linalg.lstsq(jac(x), fun(x), rcond=None)[0]
    assert lin.converged
    np.testing.assert_allclose(lin.x_g, x[:P_g], rtol=1e-9, atol=1e-12)
    r = fun(x)
    assert abs(lin.chi2 - r @ r) <= 1e-9 * lin.chi2


def test_a_term_on_the_motions_gyro_samples_has_the_columns_its_differenced_residuals_give(fitted):
    """``gyro_columns``: the response of every row to a term added to the motions' raw gyro
    samples, through the attitude, against central differences of the residuals (more columns
    than ``GYRO_CHUNK``, formed at once)."""
    lin = fitted[-1]
    model = lin.model
    ms = model.motions
    rng = np.random.default_rng(4)
    dy = rng.standard_normal((len(ms.t), 3, 14)) * 1e-3
    dy[:, :, 0] = np.abs(ms.y)  # a rate-sign term on every axis
    J = model.gyro_columns(lin.x_g, lin.x_l, dy)[:]
    for c in (0, 5, 13):
        h = 1e-3

        def r(step: float) -> np.ndarray:
            m = copy.copy(model)
            m.motions = dataclasses.replace(ms, y=ms.y + step * dy[:, :, c])
            return m.residuals(lin.x_g, lin.x_l, jacobian=False)[0]

        fd = (r(h) - r(-h)) / (2 * h)
        assert np.linalg.norm(fd) > 0
        assert not np.delete(fd, model.motion_rows).any()  # no other row moves
        fd = fd[model.motion_rows]
        assert np.linalg.norm(J[:, c] - fd) < 1e-6 * np.linalg.norm(fd)


def test_a_factored_gyro_term_has_the_columns_of_its_dense_form(fitted):
    """A library's gyro columns come factored (a few signals, each on one axis): the same
    columns as the dense (N_g, 3, k) term, without forming it."""
    lin = fitted[-1]
    model = lin.model
    ms = model.motions
    signals = np.column_stack([np.abs(ms.y[:, 0]), ms.y[:, 1] ** 2])  # two signals ...
    basis = np.zeros((2, 3, 14))
    for j in range(14):  # ... each column one of them on one axis
        basis[j % 2, j % 3, j] = 1.0
    dense = np.einsum("nu,ubk->nbk", signals, basis)
    want = model.gyro_columns(lin.x_g, lin.x_l, dense)[:]
    got = model.gyro_columns(lin.x_g, lin.x_l, RateDerivatives(signals, basis))[:]
    assert np.abs(want).max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())


def test_gyro_columns_read_by_slices_of_rows_are_the_same_bits(fitted, monkeypatch):
    """A structure cell reads a library's gyro columns by slices of rows as it goes: any slices,
    across the turns' rows and blocks of samples, give the bits of the whole."""
    lin = fitted[-1]
    model = lin.model
    dy = np.random.default_rng(3).normal(size=(len(model.motions.t), 3, 14))  # two chunks of columns
    whole = model.gyro_columns(lin.x_g, lin.x_l, dy)[:]
    monkeypatch.setattr(forward, "SAMPLE_CHUNK", 37)  # many blocks of samples, the last one short
    cols = model.gyro_columns(lin.x_g, lin.x_l, dy, negate=True)
    n_turn = cols.n_turn
    assert 0 < n_turn < len(cols) == len(whole)
    edges = [0, n_turn - 1, n_turn + 4, n_turn + 3 * 37 + 1, n_turn + 500, len(cols) - 2, len(cols)]
    got = np.vstack([cols[a:b] for a, b in itertools.pairwise(edges)])
    assert np.abs(whole).max() > 0 and np.array_equal(got, -whole)
    assert np.array_equal(cols[n_turn + 3:n_turn + 9], -whole[n_turn + 3:n_turn + 9])  # a block read again

"""joint_ml's bias random walks (brownian.py): the q -> 0 limit, the restricted likelihood, the fit."""

from __future__ import annotations

import numpy as np
from method_b_synth import G, make_session

from imupipe.models import TriadCalibration
from imupipe.solvers.brownian import bounded_minimum, estimate_intensity, reml_cost
from imupipe.solvers.joint_ml import JointML, JointMLParams, JointObservations

TINY_RW = 1e-12  # rad/s/sqrt(s): q = 1e-24, far below any rest's white variance


def _solve(s, **params):
    accel = TriadCalibration("accel", np.linalg.inv(s.S_accel), s.b_accel)
    gyro = TriadCalibration("gyro", np.linalg.inv(s.S_gyro), s.b_gyro)
    return JointML().solve(JointObservations(s.rests, s.turns, G, accel, gyro), JointMLParams(**params))


def test_vanishing_walk_is_the_constant_bias_model():
    s = make_session(11)
    const = _solve(s, gyro_bias_rw=0.0, accel_bias_rw=0.0)
    tiny = _solve(s, gyro_bias_rw=TINY_RW, accel_bias_rw=TINY_RW)  # walk states with q -> 0
    for sensor in ("accel", "gyro"):
        np.testing.assert_allclose(tiny.triads[sensor].M, const.triads[sensor].M, rtol=0, atol=1e-9)
        np.testing.assert_allclose(tiny.triads[sensor].b0, const.triads[sensor].b0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(tiny.details["chi2"], const.details["chi2"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(tiny.cov, const.cov, rtol=1e-4, atol=1e-16)


def test_white_noise_session_estimates_no_walk():
    s = make_session(11)
    d = _solve(s).details
    assert d["gyro_bias_walk"]["estimated"] and d["gyro_bias_walk"]["q"] == [0.0, 0.0, 0.0]
    assert d["accel_bias_walk"]["estimated"] and d["accel_bias_walk"]["q"] == [0.0, 0.0, 0.0]


def _dense_reml(q, t_start, t_end, r, var, X, h=0.05):
    """-2 log restricted likelihood from the walk discretised on a fine grid (independent of the
    boundary-state representation)."""
    t = np.arange(t_start.min(), t_end.max(), h) + h / 2
    A = np.array([(t >= a) & (t < b) for a, b in zip(t_start, t_end, strict=True)], float)
    A /= A.sum(axis=1, keepdims=True)
    V = np.diag(var) + q * A @ np.minimum.outer(t - t_start.min(), t - t_start.min()) @ A.T
    L = np.linalg.cholesky(V)
    Lr, LX = np.linalg.solve(L, r), np.linalg.solve(L, X)
    XtX = LX.T @ LX
    e = Lr - LX @ np.linalg.solve(XtX, LX.T @ Lr)
    return 2 * np.log(np.diag(L)).sum() + np.linalg.slogdet(XtX)[1] + e @ e


def test_restricted_likelihood_matches_a_discretised_walk():
    rng = np.random.default_rng(3)
    n = 12
    t_start = np.cumsum(rng.uniform(6, 9, n))
    t_end = t_start + rng.uniform(2, 4, n)
    r = rng.normal(size=n) * 1e-3
    var = np.full(n, 1e-6)
    X = np.column_stack([np.ones(n), rng.normal(size=n)])
    for q in (1e-9, 1e-7):
        dense = _dense_reml(q, t_start, t_end, r, var, X)
        assert abs(reml_cost(q, t_start, t_end, r, var, X) - dense) < 0.02, q
    shift = t_start[5] - t_end[4]  # intervals that touch share a boundary state
    t_start[5:] -= shift
    t_end[5:] -= shift
    for q in (1e-9, 1e-7):
        dense = _dense_reml(q, t_start, t_end, r, var, X)
        assert abs(reml_cost(q, t_start, t_end, r, var, X) - dense) < 0.02, q


def test_walk_is_found_and_jumps_are_scatter_not_walk():
    rng = np.random.default_rng(5)
    n = 150
    t_start = np.arange(n) * 10.0
    t_end = t_start + 5.0
    var = np.full((n, 3), 1e-8)
    q = 1e-9
    walk = np.cumsum(rng.normal(size=(n, 3)) * np.sqrt(q * 10.0), axis=0)
    est, _ = estimate_intensity(t_start, t_end, walk + rng.normal(size=(n, 3)) * 1e-4, var, np.ones((n, 1)))
    assert 0.3 * q < est < 3 * q
    quiet, _ = estimate_intensity(t_start, t_end, rng.normal(size=(n, 3)) * 1e-4, var, np.ones((n, 1)))
    assert quiet == 0.0
    jumps = rng.normal(size=(n, 3)) * 3e-4  # independent rest-to-rest scatter, no time correlation
    est, nu = estimate_intensity(t_start, t_end, jumps, var, np.ones((n, 1)))
    assert est < 0.1 * q and nu > 0


def test_a_weak_walk_the_detection_misses_is_still_estimated_at_the_likelihoods_maximum():
    n = 60
    t_start = np.arange(n) * 6.0
    t_end, var, q = t_start + 3.0, np.full((n, 3), 1e-8), 2e-11  # a walk of the noise's size over the span
    detected, estimated = [], []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        r = np.cumsum(rng.normal(size=(n, 3)) * np.sqrt(q * 6.0), axis=0) + rng.normal(size=(n, 3)) * 1e-4
        detected.append(estimate_intensity(t_start, t_end, r, var, np.ones((n, 1)))[0])
        estimated.append(estimate_intensity(t_start, t_end, r, var, np.ones((n, 1)), min_lr=0.0)[0])
    detected, estimated = np.array(detected), np.array(estimated)
    missed = detected == 0
    assert 2 <= missed.sum() <= 8
    np.testing.assert_array_equal(estimated[~missed], detected[~missed])
    assert np.all(estimated[missed] > 0)
    assert 0.3 * q < np.median(estimated) < 3 * q


def test_bounded_minimum_takes_scipys_steps_to_the_bit():
    from scipy.optimize import minimize_scalar

    rng = np.random.default_rng(2)
    n = 80
    t_start = np.arange(n) * 8.0
    t_end, var = t_start + 4.0, np.full(n, 1e-8)
    r = np.cumsum(rng.normal(size=n) * np.sqrt(1e-10 * 8.0)) + rng.normal(size=n) * 1e-4
    X = np.ones((n, 1))

    def reml(x):
        return reml_cost(10.0**x, t_start, t_end, r, var, X)

    cases = [(reml, -11.5, -8.5, 0.01), (lambda x: (x - 2) * x * (x + 2) ** 2, -3.0, -1.0, 1e-5),
             (lambda x: abs(x - 0.3), 0.0, 1.0, 1e-5), (lambda x: -x, 0.0, 1.0, 1e-5),  # at an edge
             (lambda x: 1.0, 0.0, 1.0, 1e-5)]  # flat
    for f, lo, hi, xatol in cases:
        seen, ours_seen = [], []
        ref = minimize_scalar(lambda x: seen.append(x) or f(x), bounds=(lo, hi), method="bounded",
                              options={"xatol": xatol})
        x, fx = bounded_minimum(lambda x: ours_seen.append(x) or f(x), lo, hi, xatol=xatol)
        assert ours_seen == seen
        assert (x, fx) == (ref.x, ref.fun)

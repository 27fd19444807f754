"""joint_ml's gyro bias random walk (bias_walk.py): the q -> 0 limit and the smoother."""

from __future__ import annotations

import numpy as np
from method_b_synth import G, make_session

from imupipe.models import TriadCalibration
from imupipe.observations import Rests, Turns
from imupipe.solvers.bias_walk import BiasWalk, centred_kernel, estimate_intensity
from imupipe.solvers.joint_ml import JointML, JointMLParams, JointObservations

TINY_RW = 1e-12  # rad/s/sqrt(s): q = 1e-24, far below any rest's white variance


def _solve(s, **params):
    accel = TriadCalibration("accel", np.linalg.inv(s.S_accel), s.b_accel)
    gyro = TriadCalibration("gyro", np.linalg.inv(s.S_gyro), s.b_gyro)
    return JointML().solve(JointObservations(s.rests, s.turns, G, accel, gyro), JointMLParams(**params))


def test_vanishing_walk_is_the_constant_bias_model():
    s = make_session(11)
    const = _solve(s, gyro_bias_rw=0.0)
    tiny = _solve(s, gyro_bias_rw=TINY_RW)  # the dense (correlated) path with q -> 0
    for sensor in ("accel", "gyro"):
        np.testing.assert_allclose(tiny.triads[sensor].M, const.triads[sensor].M, rtol=0, atol=1e-9)
        np.testing.assert_allclose(tiny.triads[sensor].b0, const.triads[sensor].b0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(tiny.details["chi2"], const.details["chi2"], rtol=1e-6)
    np.testing.assert_allclose(tiny.cov, const.cov, rtol=1e-5, atol=1e-16)


def test_white_noise_session_estimates_no_walk():
    s = make_session(11)
    walk = _solve(s).details["gyro_bias_walk"]
    assert walk["estimated"] and walk["q"] == [0.0, 0.0, 0.0]


def _rests(t_start: np.ndarray, length: float, gyro: np.ndarray, white_var: float) -> Rests:
    n = len(t_start)
    cov = np.broadcast_to(white_var * np.eye(3), (n, 3, 3)).copy()
    counts = np.full(n, 100)
    return Rests(t_start, t_start + length, counts, {"gyro": gyro}, {"gyro": cov},
                 np.full(n, np.nan), {"gyro": counts})


def _discrete_walk_cov(intervals: list[tuple[float, float]], span: float, h: float = 0.02) -> np.ndarray:
    """Covariance of the averages over ``intervals`` of a unit Wiener process minus its mean
    over ``[0, span]``, from the process on a grid of step ``h`` (independent of the
    closed form in ``centred_kernel``)."""
    t = np.arange(0.5 * h, span, h)
    A = np.array([(t >= a) & (t < b) for a, b in intervals], float)
    A = A / A.sum(axis=1, keepdims=True) - 1.0 / len(t)  # average minus the session mean
    return A @ np.minimum.outer(t, t) @ A.T


def test_smoother_interpolates_between_rests_and_knows_its_uncertainty():
    """Precise, short rests and a strong walk: a turn midway between two rests takes their
    mean bias; its uncertainty is the Gaussian conditional of the walk's discretised
    covariance; no walk: offset and variance zero."""
    t_start = np.arange(6) * 10.0
    gyro = np.array([[0, 0, 0], [1, 2, 3], [2, 2, 2], [4, 0, 1], [3, 1, 0], [0, 0, 0]]) * 1e-4
    rests = _rests(t_start, 1e-3, gyro, 1e-12)  # white variance of a mean 1e-14: small
    turn_t = np.linspace(13.0, 17.0, 41)  # between rest 1 (at 10) and rest 2 (at 20)
    turns = Turns(np.array([1]), np.array([2]), (turn_t,), (np.zeros((41, 3)),))
    q = 1e-8
    walk = BiasWalk.build(rests, turns, np.full(3, q))
    X = np.kron(np.ones((len(t_start), 1)), np.eye(3))  # the level b0, by GLS
    level = np.linalg.lstsq(walk.whitener @ X, walk.whitener @ gyro.ravel(), rcond=None)[0]
    np.testing.assert_allclose(level + walk.offsets(gyro - level)[0], gyro[1:3].mean(axis=0),
                               rtol=0, atol=1e-8)
    # rests of 1 s (the grid resolves them), the same turn
    rests = _rests(t_start, 1.0, gyro, 1e-12)
    walk = BiasWalk.build(rests, turns, np.full(3, q))
    C = q * _discrete_walk_cov([(a, a + 1.0) for a in t_start] + [(13.0, 17.0)], 51.0)
    C[np.arange(6), np.arange(6)] += 1e-14
    P = C[6, 6] - C[6, :6] @ np.linalg.solve(C[:6, :6], C[:6, 6])
    np.testing.assert_allclose(walk.cov[0], P * np.eye(3), rtol=0.01, atol=1e-3 * P)
    none = BiasWalk.build(rests, turns, np.zeros(3))
    assert not none.active and np.all(none.offsets(gyro) == 0) and np.all(none.cov == 0)


def test_intensity_recovers_a_simulated_walk():
    rng = np.random.default_rng(3)
    n, period, length, q, white_var = 200, 9.0, 5.0, 1e-10, 1e-12
    t_start = np.arange(n) * period
    steps = rng.normal(0, np.sqrt(q * period), (n, 3))
    gyro = 0.01 + np.cumsum(steps, axis=0) + rng.normal(0, np.sqrt(white_var / 100), (n, 3))
    rests = _rests(t_start, length, gyro, white_var)
    est, _ = estimate_intensity(rests, gyro - gyro.mean(axis=0), np.ones((n, 1)))
    assert np.all(np.abs(np.log(est / q)) < np.log(1.5)), est
    quiet = rests.need("gyro")[:1] + rng.normal(0, np.sqrt(white_var / 100), (n, 3))
    q0, _ = estimate_intensity(_rests(t_start, length, quiet, white_var), quiet - quiet.mean(0),
                               np.ones((n, 1)))
    assert np.all(q0 == 0)
    # a scatter from rest to rest without time correlation is not a walk
    jumps = quiet + rng.normal(0, 1e-5, (n, 3))
    q1, nu = estimate_intensity(_rests(t_start, length, jumps, white_var), jumps - jumps.mean(0),
                                np.ones((n, 1)))
    assert np.all(q1 == 0) and 0.3e-5 < np.sqrt(nu) < 3e-5
    # collinear regressors (a session at one attitude: the gravity columns are constant)
    X = np.column_stack([np.ones(n), np.ones((n, 3)) * [0.1, 0.2, 0.97]])
    q2, _ = estimate_intensity(rests, gyro - gyro.mean(axis=0), X)
    np.testing.assert_allclose(q2, est, rtol=1e-6)


def test_centred_kernel_averages_to_zero_over_the_session():
    """Point values (zero length) average to zero; interval averages: PSD, and the
    discretised process's covariance."""
    t = np.linspace(0.0, 100.0, 2001)
    zero = np.zeros_like(t)
    K = centred_kernel(t, zero, t, zero, 0.0, 100.0)
    row_means = np.trapezoid(K, t, axis=1) / 100.0
    assert np.abs(row_means).max() < 1e-3 * K.max()
    mid, length = np.arange(200) * 9.0 + 2.5, np.full(200, 5.0)
    K = centred_kernel(mid, length, mid, length, 0.0, 1800.0, same=True)
    assert np.linalg.eigvalsh(K).min() > 0
    intervals = [(0.0, 1.0), (4.0, 9.0), (20.0, 22.0), (30.0, 40.0)]
    mid = np.array([0.5 * (a + b) for a, b in intervals])
    length = np.array([b - a for a, b in intervals])
    np.testing.assert_allclose(centred_kernel(mid, length, mid, length, 0.0, 40.0, same=True),
                               _discrete_walk_cov(intervals, 40.0), rtol=0, atol=0.01)

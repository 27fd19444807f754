"""Method B solvers: exact rotation integration, ellipsoid by SVD, gyro by integration."""

from __future__ import annotations

import numpy as np
import pytest
from method_b_synth import G, make_session

from imupipe.errors import SolverError
from imupipe.observations import EllipsoidObservations, GyroObservations, Turns
from imupipe.rotations import (
    centred_intervals,
    compose,
    hold_intervals,
    pad_turns,
    quat_exp,
    quat_mul,
    quat_to_matrix,
    ragged_turn_quaternions,
    ragged_turn_rotations,
    rotation_angle,
    turn_quaternions,
    turn_rotations,
)
from imupipe.solvers.ellipsoid_svd import EllipsoidSVD, EllipsoidSVDParams, fit_quadric
from imupipe.solvers.gyro_integration import (
    GyroIntegration,
    GyroIntegrationParams,
    saturated_turns,
)

ACC_BIAS_TOL_MG = 0.2          # per axis, 1 mg = 9.80665e-3 m/s^2
ACC_SHAPE_TOL_PPM = 200.0      # max |M_est S_true - I| entry
GYRO_SHAPE_TOL_PPM = 600.0     # max entry of M_est S_true - I (scale and alignment in one)
GYRO_BIAS_TOL_DPS = 0.002      # deg/s
MG = 9.80665e-3


def test_compose_equals_sequential_product():
    rng = np.random.default_rng(3)
    q = quat_exp(rng.normal(size=(4, 37, 3)) * 0.3)
    seq = np.tile([1.0, 0, 0, 0], (4, 1))
    for k in range(37):
        seq = quat_mul(seq, q[:, k])
    np.testing.assert_allclose(compose(q), seq, atol=1e-13)


def test_constant_rate_gives_exact_angle_and_padding_is_neutral():
    t = np.arange(250) * 0.01
    w = np.tile([0.0, 0.0, np.radians(72.0)], (250, 1))  # 72 deg/s for 2.5 s = 180 deg
    rate, dt = pad_turns([t, t[:10]], [w, w[:10]])
    R = turn_rotations(rate, dt)
    np.testing.assert_allclose(np.degrees(rotation_angle(R)), [180.0, 7.2], atol=1e-9)
    alone = turn_rotations(*pad_turns([t[:10]], [w[:10]]))
    np.testing.assert_allclose(R[1], alone[0], atol=1e-15)


def test_turns_of_mixed_lengths_are_the_products_of_the_whole_padded_arrays(monkeypatch):
    rng = np.random.default_rng(5)
    lengths = [*rng.integers(300, 420, 40), 2000, 1, 0]  # short turns, a turntable's, degenerate ones
    rate, dt = pad_turns([np.arange(n) * 0.01 for n in lengths], [rng.normal(size=(n, 3)) for n in lengths])
    whole = quat_to_matrix(compose(quat_exp(rate * dt[..., None])))
    assert np.array_equal(turn_rotations(rate, dt), whole)  # grouped by length: the same bits
    # corrected by M and picked by index a few turns at a time: the bits of the whole corrected copy
    M = np.eye(3) + 0.02 * rng.normal(size=(3, 3))
    pick = rng.permutation(len(lengths))[:30]
    corrected = quat_to_matrix(compose(quat_exp((rate @ M.T)[pick] * dt[pick][..., None])))
    monkeypatch.setattr("imupipe.rotations.TURN_CHUNK", 7)
    assert np.array_equal(turn_rotations(rate, dt, M, pick), corrected)


def test_ragged_turns_are_the_padded_turns_products_to_the_bit(monkeypatch):
    """Turns padded by groups of similar length, not all to the longest: the same numbers as the
    padded arrays less each turn's bias, with and without M, for both kinds of interval."""
    rng = np.random.default_rng(8)
    lengths = [*rng.integers(300, 420, 70), 2000, 150, 1, 0, 700]
    t = [np.sort(rng.uniform(0, n * 0.01, n)) for n in lengths]
    w = [rng.normal(size=(n, 3)) for n in lengths]
    bias = 0.01 * rng.normal(size=(len(lengths), 3))
    M = np.eye(3) + 0.02 * rng.normal(size=(3, 3))
    monkeypatch.setattr("imupipe.rotations.TURN_CHUNK", 16)  # groups of several chunks
    for intervals in (hold_intervals, centred_intervals):
        rate, dt = pad_turns(t, w, intervals)
        rate -= bias[:, None, :]
        for m in (None, M):
            assert np.array_equal(ragged_turn_quaternions(t, w, intervals, bias, m), turn_quaternions(rate, dt, m))
            assert np.array_equal(ragged_turn_rotations(t, w, intervals, bias, m), turn_rotations(rate, dt, m))
        rate, dt = pad_turns(t, w, intervals)
        assert np.array_equal(ragged_turn_quaternions(t, w, intervals), turn_quaternions(rate, dt))


def test_quat_exp_small_angles_match_series():
    phi = np.array([[1e-9, -2e-9, 3e-9], [0.2, 0.1, -0.3]])
    R = quat_to_matrix(quat_exp(phi))
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-14)
    np.testing.assert_allclose(rotation_angle(R)[1], np.linalg.norm(phi[1]), atol=1e-12)


def _accel_obs(seed: int, **kw) -> tuple[EllipsoidObservations, object]:
    s = make_session(seed, **kw)
    r = s.rests
    return EllipsoidObservations("accel", r.mean["accel"], r.cov_of_mean("accel"), r.temperature, G), s


def test_quadric_is_exact_without_noise():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(30, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    S = np.array([[0.9, 0, 0], [0.01, 1.1, 0], [-0.02, 0.03, 1.05]])
    b = np.array([0.3, -0.1, 0.2])
    W, b_fit, _ = fit_quadric((G * u) @ S.T + b, G)
    np.testing.assert_allclose(b_fit, b, atol=1e-10)
    np.testing.assert_allclose(W, np.linalg.inv(S @ S.T), atol=1e-10)


@pytest.mark.parametrize("seed", [0, 1])
def test_ellipsoid_svd_recovers_accelerometer(seed):
    obs, s = _accel_obs(seed, sigma_accel=0.005)
    fit = EllipsoidSVD().solve(obs, EllipsoidSVDParams())
    # S_ACCEL is lower-triangular, the frame ellipsoid_svd returns (Eq. (1.3)).
    shape_ppm = np.abs(fit.M @ s.S_accel - np.eye(3)).max() * 1e6
    bias_mg = np.abs(fit.b0 - s.b_accel).max() / MG
    assert shape_ppm < ACC_SHAPE_TOL_PPM, shape_ppm
    assert bias_mg < ACC_BIAS_TOL_MG, bias_mg
    assert np.allclose(np.triu(np.linalg.inv(fit.M), 1), 0.0, atol=1e-15)
    sigma = np.sqrt(np.diag(fit.cov))
    err = np.concatenate([(fit.M - np.linalg.inv(s.S_accel)).ravel(), fit.b0 - s.b_accel])
    free = sigma > 0
    assert np.all(np.abs(err[free]) < 5 * sigma[free])  # the covariance is honest


def test_symmetric_root_fits_the_same_ellipsoid():
    obs, _ = _accel_obs(2)
    chol = EllipsoidSVD().solve(obs, EllipsoidSVDParams())
    sym = EllipsoidSVD().solve(obs, EllipsoidSVDParams(square_root="symmetric"))
    np.testing.assert_allclose(sym.M.T @ sym.M, chol.M.T @ chol.M, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sym.M, sym.M.T, atol=1e-12)
    upper = EllipsoidSVD().solve(obs, EllipsoidSVDParams(square_root="upper_correction"))
    np.testing.assert_allclose(upper.M.T @ upper.M, chol.M.T @ chol.M, rtol=1e-9, atol=1e-12)
    assert np.allclose(np.tril(upper.M, -1), 0.0, atol=1e-15)  # imu_tk's T K
    assert np.all(np.isfinite(np.diag(upper.cov)))


def test_ellipsoid_svd_says_how_many_positions_are_missing():
    obs, _ = _accel_obs(0, n_rests=7)
    with pytest.raises(SolverError, match="at least 2 more"):
        EllipsoidSVD().solve(obs, EllipsoidSVDParams())


def _gyro_obs(s, gravity=None) -> GyroObservations:
    r = s.rests
    g = s.gravity_body if gravity is None else gravity
    return GyroObservations(g, r.mean["gyro"], r.cov_of_mean("gyro"), s.turns)


@pytest.mark.parametrize("fit_bias", [False, True])
def test_gyro_integration_recovers_gyroscope(fit_bias):
    s = make_session(5)
    fit = GyroIntegration().solve(_gyro_obs(s), GyroIntegrationParams(fit_bias=fit_bias))
    shape_ppm = np.abs(fit.M @ s.S_gyro - np.eye(3)).max() * 1e6
    bias_dps = np.degrees(np.abs(fit.b0 - s.b_gyro).max())
    assert shape_ppm < GYRO_SHAPE_TOL_PPM, shape_ppm
    assert bias_dps < GYRO_BIAS_TOL_DPS, bias_dps
    assert fit.details["rms_gravity_mismatch_deg"] < 0.1
    sigma = np.sqrt(np.diag(fit.cov))[:9]
    assert np.all(np.abs(fit.M - np.linalg.inv(s.S_gyro)).ravel() < 5 * sigma)  # honest covariance


def test_gyro_follows_the_accelerometer_frame():
    """Gravity seen in a rotated accelerometer frame: the gyro comes out in that frame."""
    s = make_session(6)
    Q = quat_to_matrix(np.array([0.99, 0.05, -0.08, 0.1]))
    fit = GyroIntegration().solve(_gyro_obs(s, s.gravity_body @ Q.T), GyroIntegrationParams())
    assert np.abs(fit.M @ s.S_gyro - Q).max() < GYRO_SHAPE_TOL_PPM * 1e-6


def test_gyro_integration_says_more_turns_are_needed():
    s = make_session(0, n_rests=4)
    with pytest.raises(SolverError, match="more turns"):
        GyroIntegration().solve(_gyro_obs(s), GyroIntegrationParams())


def test_axis_aligned_quadric_from_six_poses():
    S = np.diag([0.99, 1.01, 1.02])
    b = np.array([0.5, -0.6, 0.4])
    up = np.vstack([np.eye(3), -np.eye(3)])
    y = (G * up) @ S.T + b
    obs = EllipsoidObservations("accel", y, np.tile(np.eye(3) * 1e-8, (6, 1, 1)), np.full(6, np.nan), G)
    fit = EllipsoidSVD().solve(obs, EllipsoidSVDParams(misalignment=False))
    np.testing.assert_allclose(np.linalg.inv(fit.M), S, atol=1e-9)
    np.testing.assert_allclose(fit.b0, b, atol=1e-9)
    with pytest.raises(SolverError, match="misalignment = false"):
        EllipsoidSVD().solve(obs, EllipsoidSVDParams())


def _clip(s, limit):
    return type(s.turns)(s.turns.before, s.turns.after, s.turns.t,
                         tuple(np.clip(w, -limit, limit) for w in s.turns.gyro))


def test_clipped_turns_are_found_left_out_and_warned():
    s = make_session(7, n_rests=30, speed_dps=120.0)
    limit = np.radians(110.0)  # peaks reach ~140 deg/s on some turns, on several axes
    clipped = _clip(s, limit)
    bad, n, _ = saturated_turns(clipped)
    bad_known, _, _ = saturated_turns(clipped, limit)
    peaks = np.array([np.abs(w).max() for w in s.turns.gyro]) >= limit
    assert n > 0 and bad.sum() >= 2
    np.testing.assert_array_equal(bad_known, peaks)
    assert np.all(bad <= peaks)  # never flags a turn that did not clip
    obs = GyroObservations(s.gravity_body, s.rests.mean["gyro"], s.rests.cov_of_mean("gyro"), clipped)
    with pytest.warns(UserWarning, match="saturated gyro samples"):
        fit = GyroIntegration().solve(obs, GyroIntegrationParams())
    assert fit.details["turns_saturated"] == bad.sum()
    assert np.abs(fit.M @ s.S_gyro - np.eye(3)).max() * 1e6 < GYRO_SHAPE_TOL_PPM


def test_one_axis_plateau_is_not_clipping():
    """A constant-rate turn sits at one axis's extreme for many samples: not a rail."""
    t = np.arange(300) * 0.01
    w = np.zeros((300, 3))
    w[50:250, 2] = 1.5  # 200 samples at the z maximum
    w[:, 0] = 0.01 * np.sin(t)
    turns = Turns(np.array([0]), np.array([1]), (t,), (w,))
    bad, n, _ = saturated_turns(turns)
    assert not bad.any() and n == 0

"""Joint maximum-likelihood refinement: recovery, frame keeping, honest covariance."""

from __future__ import annotations

import numpy as np
import pytest
from method_b_synth import G, make_session

from imupipe.errors import SolverError
from imupipe.models import TriadCalibration
from imupipe.rotations import quat_to_matrix
from imupipe.solvers.joint_ml import JointML, JointMLParams, JointObservations, covariance_at_start

ACC_BIAS_TOL_MG = 0.2
ACC_SHAPE_TOL_PPM = 200.0
GYRO_SHAPE_TOL_PPM = 600.0
MG = 9.80665e-3
Z_MAX = 5.0  # largest error in units of the reported sigma


def _start(s, Q=None, error=1e-3, seed=0):
    """A rough start (errors ~1e-3): lower-triangular accelerometer, turned by Q if given."""
    rng = np.random.default_rng(seed)
    Q = np.eye(3) if Q is None else Q
    S0 = s.S_accel + np.tril(error * rng.normal(size=(3, 3)))
    Ma = Q @ np.linalg.inv(S0)
    Mg = Q @ np.linalg.inv(s.S_gyro) @ (np.eye(3) + error * rng.normal(size=(3, 3)))
    return (TriadCalibration("accel", Ma, s.b_accel + 0.05 * rng.normal(size=3)),
            TriadCalibration("gyro", Mg, s.b_gyro + 1e-3 * rng.normal(size=3)))


def _solve(s, accel, gyro, **params):
    return JointML().solve(JointObservations(s.rests, s.turns, G, accel, gyro), JointMLParams(**params))


def _truth_vector(s):
    return np.concatenate([np.linalg.inv(s.S_accel).ravel(), s.b_accel,
                           np.linalg.inv(s.S_gyro).ravel(), s.b_gyro])


def test_joint_ml_recovers_both_triads_with_honest_sigmas():
    s = make_session(11)
    fit = _solve(s, *_start(s))
    a, g = fit.triads["accel"], fit.triads["gyro"]
    assert np.abs(a.M @ s.S_accel - np.eye(3)).max() * 1e6 < ACC_SHAPE_TOL_PPM
    assert np.abs(a.b0 - s.b_accel).max() / MG < ACC_BIAS_TOL_MG
    assert np.abs(g.M @ s.S_gyro - np.eye(3)).max() * 1e6 < GYRO_SHAPE_TOL_PPM
    est = np.concatenate([a.M.ravel(), a.b0, g.M.ravel(), g.b0])
    sigma = np.sqrt(np.diag(fit.cov))[:24]
    free = sigma > 1e-12  # the three fixed upper entries of the accelerometer
    assert free.sum() == 21
    z = np.abs(est - _truth_vector(s))[free] / sigma[free]
    assert z.max() < Z_MAX, z.max()
    assert 0.7 < fit.details["chi2_per_dof"] < 1.3


def test_joint_ml_keeps_the_frame_of_its_start():
    s = make_session(12)
    Q = quat_to_matrix(np.array([0.98, 0.1, -0.12, 0.1]))
    fit = _solve(s, *_start(s, Q))
    a, g = fit.triads["accel"], fit.triads["gyro"]
    assert np.abs(a.M @ s.S_accel - Q).max() < ACC_SHAPE_TOL_PPM * 1e-6  # frame kept
    assert np.abs(g.M @ s.S_gyro - Q).max() < GYRO_SHAPE_TOL_PPM * 1e-6
    lower = _solve(s, *_start(s, Q), keep_frame=False).triads["accel"]
    assert np.allclose(np.triu(np.linalg.inv(lower.M), 1), 0.0, atol=1e-12)


def test_covariance_at_truth_is_the_cramer_rao_bound_of_a_monte_carlo():
    """Empirical RMS error over seeds within 1.5x of sqrt(CRB) (small run; bench has more)."""
    errs, crb = [], []
    for seed in range(12):
        s = make_session(100 + seed, n_rests=25)
        fit = _solve(s, *_start(s, seed=seed))
        a, g = fit.triads["accel"], fit.triads["gyro"]
        errs.append(np.concatenate([a.M.ravel(), a.b0, g.M.ravel(), g.b0]) - _truth_vector(s))
        truth = (TriadCalibration("accel", np.linalg.inv(s.S_accel), s.b_accel),
                 TriadCalibration("gyro", np.linalg.inv(s.S_gyro), s.b_gyro))
        cov = covariance_at_start(JointObservations(s.rests, s.turns, G, *truth),
                                  JointMLParams(gyro_bias_rw=0.0, accel_bias_rw=0.0))
        crb.append(np.diag(cov)[:24])
    bound = np.sqrt(np.mean(crb, axis=0))
    free = bound > 1e-12
    ratio = np.sqrt(np.mean(np.square(errs), axis=0))[free] / bound[free]
    # 12 seeds: a ratio's own scatter is ~20 %, so the mean tests efficiency, the max sanity.
    assert 0.75 < ratio.mean() < 1.25, ratio
    assert ratio.max() < 1.8, ratio


def test_joint_ml_needs_turns():
    s = make_session(13, n_rests=4)
    with pytest.raises(SolverError, match="at least 9 rests and 5 turns"):
        _solve(s, *_start(s))


K_ACCEL = np.array([2e-3, -1.5e-3, 1e-3])  # m/s^2 per degC (~0.2 mg/degC)
K_GYRO = np.array([1.7e-4, -1.2e-4, 0.9e-4])  # rad/s per degC (~0.01 deg/s/degC)
K_ACCEL_TOL = 2e-4  # m/s^2 per degC
K_GYRO_TOL = 1e-5  # rad/s per degC


def test_joint_ml_fits_temperature_coefficients_of_a_warming_session():
    s = make_session(14, n_rests=80, k_accel=K_ACCEL, k_gyro=K_GYRO)
    assert np.ptp(s.rests.temperature) > 10
    fit = _solve(s, *_start(s))
    assert fit.details["fitted_temperature_coefficients"]
    assert np.abs(fit.k["accel"] - K_ACCEL).max() < K_ACCEL_TOL
    assert np.abs(fit.k["gyro"] - K_GYRO).max() < K_GYRO_TOL
    assert np.all(np.abs(fit.k["gyro"] - K_GYRO) < Z_MAX * fit.sigma_k["gyro"])
    a, g = fit.triads["accel"], fit.triads["gyro"]
    assert np.abs(a.b0 - s.b_accel).max() / MG < ACC_BIAS_TOL_MG
    assert np.abs(a.M @ s.S_accel - np.eye(3)).max() * 1e6 < ACC_SHAPE_TOL_PPM
    assert np.abs(g.M @ s.S_gyro - np.eye(3)).max() * 1e6 < GYRO_SHAPE_TOL_PPM
    without = _solve(s, *_start(s), fit_temperature="no")  # the drift then biases the fit
    assert np.abs(without.triads["accel"].b0 - s.b_accel).max() > np.abs(a.b0 - s.b_accel).max()


def test_a_thermal_stage_k_enters_as_a_prior():
    s = make_session(15, n_rests=40, k_accel=K_ACCEL, k_gyro=K_GYRO)
    accel, gyro = _start(s)
    tight = 1e-7  # per degC: a warm-up fit far better than the rests can do
    accel = TriadCalibration("accel", accel.M, accel.b0, K_ACCEL, details={"sigma_k": [tight] * 3})
    gyro = TriadCalibration("gyro", gyro.M, gyro.b0, K_GYRO, details={"sigma_k": [tight] * 3})
    fit = _solve(s, accel, gyro)
    assert fit.details["k_prior_entries"] == 6
    assert np.abs(fit.k["accel"] - K_ACCEL).max() < 10 * tight
    assert np.all(fit.sigma_k["gyro"] <= tight * 1.01)
    loose = _solve(s, *_start(s))  # no prior: k from the rests alone, larger sigma
    assert np.all(loose.sigma_k["accel"] > fit.sigma_k["accel"])

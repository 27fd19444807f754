"""Method A ellipsoid solvers (accel eqs. 7-20, mag eqs. 21-25): recovery against known truth."""

from __future__ import annotations

import numpy as np
import pytest
from method_a_synth import B_ACC, S_ACC, G, unit_sphere
from scipy.spatial.transform import Rotation

from imupipe.errors import SolverError
from imupipe.observations import EllipsoidObservations
from imupipe.solvers.ellipsoid_cholesky import EllipsoidCholesky, EllipsoidParams
from imupipe.solvers.mag_dip import MagDip, MagDipParams, circle_dip

ACC_BIAS_TOL_MG = 0.3  # paper Table 1, N = 200, sigma 0.5 mg: 95 % within +-0.14 mg
ACC_M_TOL_PPM = 1500  # rotation from ONE noisy reference rest (0.5 mg / g = 500 urad 1-sigma)
ACC_SHAPE_TOL_PPM = 600  # M^T M (no reference rests): paper Tables 2-3 give 95 % +-0.38 mg at N = 200, i.e. ~190 ppm 1-sigma
MAG_M_TOL = 0.002  # 0.2 %: the mag shape target
NOISE_MG = 0.5


def accel_obs(n: int, seed: int, noise_mg: float = NOISE_MG, refs: bool = True) -> EllipsoidObservations:
    rng = np.random.default_rng(seed)
    x = unit_sphere(n, rng) * G
    if refs:
        x[0], x[1] = [0, G, 0], [G, 0, 0]  # instrument Y up, X up
    y = x @ S_ACC.T + B_ACC + rng.normal(size=(n, 3)) * noise_mg * 1e-3 * G
    cov = np.tile(np.eye(3) * (noise_mg * 1e-3 * G) ** 2, (n, 1, 1))
    return EllipsoidObservations("accel", y, cov, np.full(n, np.nan), G,
                                 0 if refs else None, 1 if refs else None)


def test_accel_recovers_bias_and_matrix_with_reference_rests():
    fit = EllipsoidCholesky().solve(accel_obs(200, 1), EllipsoidParams())
    bias_mg = (fit.b0 - B_ACC) / G * 1e3
    assert np.all(np.abs(bias_mg) < ACC_BIAS_TOL_MG)
    assert np.abs(fit.M @ S_ACC - np.eye(3)).max() * 1e6 < ACC_M_TOL_PPM
    sigma_mg = np.sqrt(np.diag(fit.cov))[9:] / G * 1e3
    assert np.all(np.abs(bias_mg) < 5 * sigma_mg)  # the reported uncertainty is honest
    assert fit.details["frame"] == "reference positions"


def test_accel_noise_free_is_exact():
    fit = EllipsoidCholesky().solve(accel_obs(50, 2, noise_mg=0.0), EllipsoidParams())
    assert np.allclose(fit.M @ S_ACC, np.eye(3), atol=1e-9)
    assert np.allclose(fit.b0, B_ACC, atol=1e-9)


@pytest.mark.parametrize("frame", ["symmetric", "upper_triangular"])
def test_accel_canonical_frame_without_references(frame):
    fit = EllipsoidCholesky().solve(accel_obs(200, 3, refs=False), EllipsoidParams(canonical_frame=frame))
    W_true = np.linalg.inv(S_ACC).T @ np.linalg.inv(S_ACC)
    assert np.abs(fit.M.T @ fit.M - W_true).max() * 1e6 < ACC_SHAPE_TOL_PPM
    if frame == "symmetric":
        assert np.allclose(fit.M, fit.M.T, atol=1e-12)
    else:
        assert np.allclose(np.tril(fit.M, -1), 0, atol=1e-12)


def test_accel_refuses_too_few_positions():
    with pytest.raises(SolverError, match="only 8 rest positions"):
        EllipsoidCholesky().solve(accel_obs(8, 4), EllipsoidParams())


def test_accel_refuses_poor_coverage():
    rng = np.random.default_rng(5)
    x = unit_sphere(100, rng)
    x[:, 2] = np.abs(x[:, 2]) * 0.05  # a thin band: z never up nor down
    x = x / np.linalg.norm(x, axis=1, keepdims=True) * G
    obs = EllipsoidObservations("accel", x @ S_ACC.T + B_ACC, np.zeros((100, 3, 3)), np.zeros(100), G)
    with pytest.raises(SolverError, match="cover the sphere poorly"):
        EllipsoidCholesky().solve(obs, EllipsoidParams())


def mag_obs(dip_deg: float, n: int, seed: int, give_dip: bool):
    rng = np.random.default_rng(seed)
    dip = np.radians(dip_deg)
    field = 50e-6
    B_n, g_n = np.array([np.cos(dip), -np.sin(dip), 0.0]) * field, np.array([0.0, 1.0, 0.0])
    att = Rotation.random(n, random_state=seed).as_matrix()
    g = np.einsum("kji,j->ki", att, g_n)
    B = np.einsum("kji,j->ki", att, B_n)
    S = np.eye(3) + rng.normal(size=(3, 3)) * 0.03
    b = np.array([10e-6, -5e-6, 3e-6])
    y = B @ S.T + b + rng.normal(size=(n, 3)) * 0.05e-6
    obs = EllipsoidObservations("mag", y, np.zeros((n, 3, 3)), np.zeros(n), field, gravity=g,
                                dip_rad=dip if give_dip else None)
    return obs, S, b


@pytest.mark.parametrize("give_dip", [True, False])
def test_mag_recovers_matrix_tied_to_gravity(give_dip):
    obs, S, b = mag_obs(65.0, 200, 6, give_dip)
    fit = MagDip().solve(obs, MagDipParams())
    assert np.abs(fit.M @ S - np.eye(3)).max() < MAG_M_TOL
    assert abs(fit.details["dip_deg"] - 65.0) < 0.05
    assert np.all(np.abs(fit.b0 - b) < 0.2e-6)


def test_mag_needs_gravity():
    obs, _, _ = mag_obs(65.0, 50, 7, True)
    obs = EllipsoidObservations("mag", obs.y, obs.cov, obs.T, obs.magnitude)
    with pytest.raises(SolverError, match="corrected accelerometer"):
        MagDip().solve(obs, MagDipParams())


def test_circle_dip_of_turntable_circles():
    dip = np.radians(71.4)
    psi = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    circle = np.column_stack([np.cos(dip) * np.cos(psi), -np.sin(dip) * np.ones_like(psi),
                              np.cos(dip) * np.sin(psi)])
    tilted = circle @ Rotation.from_rotvec([0.3, 0.1, -0.2]).as_matrix().T  # any mounting
    est, radii = circle_dip([circle, tilted])
    assert abs(np.degrees(est) - 71.4) < 1e-9
    assert np.allclose(radii, np.cos(dip))

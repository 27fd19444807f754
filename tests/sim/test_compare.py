"""Gauge-free errors against the truth: zero at the truth, and each known error read back."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.models import Calibration, TriadCalibration
from imupipe.rotations import exp_so3, random_rotation
from imupipe.sim.compare import calibration_errors, reported_sigma, triad_errors

G = 9.80665


@pytest.fixture
def truth() -> Calibration:
    rng = np.random.default_rng(7)
    triads = {}
    for sensor, bias in (("accel", 0.3), ("gyro", 0.02), ("mag", 20e-6)):
        S = np.eye(3) + 0.03 * rng.normal(size=(3, 3))
        triads[sensor] = TriadCalibration(sensor, np.linalg.inv(S), bias * rng.normal(size=3),
                                          1e-3 * bias * rng.normal(size=3))
    return Calibration(triads)


def _with(t: TriadCalibration, M=None, b0=None, k=None) -> TriadCalibration:
    return TriadCalibration(t.sensor, t.M if M is None else M, t.b0 if b0 is None else b0,
                            t.k if k is None else k)


def test_truth_against_itself_is_zero(truth):
    e = calibration_errors(truth, truth)
    assert set(e.triads) == {"accel", "gyro", "mag"}
    for value in e.as_dict().values():
        assert abs(value) < 1e-6  # ppm, deg, mg: rounding only


def test_a_turned_frame_is_its_angle_and_no_shape(truth):
    R = exp_so3(np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5]), np.radians(3.0))
    est = {s: _with(t, M=R @ t.M) for s, t in truth.triads.items()}
    e = calibration_errors(est, truth)
    for s in est:
        assert e[s].frame_deg == pytest.approx(3.0, abs=1e-9)
        assert e[s].shape_ppm < 1e-6
        np.testing.assert_allclose(e[s].Q, R, atol=1e-12)
    assert e.gyro_accel_align_deg < 1e-9  # both turned alike: aligned


def test_gyro_turned_against_accel_is_the_alignment(truth):
    R = exp_so3(np.array([0.0, 0.0, 1.0]), np.radians(0.05))
    common = random_rotation(np.random.default_rng(3))  # the free frame does not matter
    est = {"accel": _with(truth["accel"], M=common @ truth["accel"].M),
           "gyro": _with(truth["gyro"], M=common @ R @ truth["gyro"].M)}
    e = calibration_errors(est, truth)
    assert e.gyro_accel_align_deg == pytest.approx(0.05, rel=1e-6)
    assert "mag" not in e.triads


def test_scale_and_nonorthogonality_in_ppm(truth):
    H = np.eye(3)
    H[1, 1] += 150e-6
    H[0, 2] = H[2, 0] = -80e-6
    t = truth["accel"]
    e = triad_errors(_with(t, M=H @ t.M), t)
    assert e.scale_ppm == pytest.approx(150, abs=1e-3)
    assert e.nonorth_ppm == pytest.approx(80, abs=1e-3)
    assert e.shape_ppm == pytest.approx(150, abs=1e-3)
    assert e.frame_deg < 1e-9


def test_overall_scale_is_set_aside(truth):
    t = truth["mag"]
    H = np.diag([1.02, 1.02, 1.02 * (1 + 300e-6)])  # nominal field 2 % off, plus 300 ppm on z
    e = triad_errors(_with(t, M=H @ t.M), t)
    assert e.shape_ppm == pytest.approx(0.02 * 1e6 + 306, rel=1e-6)
    assert e.overall_scale_ppm == pytest.approx(((1.02**3 * (1 + 300e-6)) ** (1 / 3) - 1) * 1e6, rel=1e-9)
    assert e.shape_scale_aside_ppm == pytest.approx(200, abs=0.1)  # 300 ppm on one axis less its mean


def test_bias_and_k_in_their_units(truth):
    errors = {"accel": (0.1e-3 * G, 1e-3 * 0.02e-3 * G), "gyro": (np.radians(0.01), np.radians(1e-4)),
              "mag": (0.5e-6, 0.01e-6)}
    est = {s: _with(t, b0=t.b0 + [0, -errors[s][0], 0], k=t.k + [errors[s][1], 0, 0])
           for s, t in truth.triads.items()}
    e = calibration_errors(est, truth, g_m_s2=G)
    assert e["accel"].bias == pytest.approx(0.1) and e["accel"].bias_unit == "mg"
    assert e["accel"].k == pytest.approx(0.02e-3)
    assert e["gyro"].bias == pytest.approx(0.01) and e["gyro"].k == pytest.approx(1e-4)
    assert e["mag"].bias == pytest.approx(0.5) and e["mag"].k == pytest.approx(0.01)
    assert e.as_dict()["gyro_bias_deg_s"] == pytest.approx(0.01)


def test_first_order_agrees_with_the_linear_split(truth):
    """Small errors: H - I is the symmetric part of E = M_est S_true - I, Q the skew part."""
    E = 1e-4 * np.random.default_rng(5).normal(size=(3, 3))
    t = truth["gyro"]
    e = triad_errors(_with(t, M=(np.eye(3) + E) @ t.M), t)
    sym, skew = 0.5 * (E + E.T), 0.5 * (E - E.T)
    assert e.scale_ppm == pytest.approx(np.abs(np.diag(sym)).max() * 1e6, abs=0.05)
    assert e.nonorth_ppm == pytest.approx(np.abs(sym - np.diag(np.diag(sym))).max() * 1e6, abs=0.05)
    angle = np.linalg.norm([skew[2, 1], skew[0, 2], skew[1, 0]])
    assert e.frame_deg == pytest.approx(np.degrees(angle), rel=1e-3)


def test_reported_sigma_in_the_same_units():
    sigma_M = np.full((3, 3), 20e-6)
    sigma_M[np.diag_indices(3)] = [10e-6, 40e-6, 30e-6]
    t = TriadCalibration("accel", np.eye(3), details={"sigma_M": sigma_M.tolist(), "sigma_b0": [1e-3, 2e-3, 0]})
    sd = reported_sigma(t, G)
    assert sd["scale_ppm"] == pytest.approx(40) and sd["nonorth_ppm"] == pytest.approx(20)
    assert sd["shape_ppm"] == pytest.approx(40)
    assert sd["frame_deg"] == pytest.approx(np.degrees(20e-6))
    assert sd["bias"] == pytest.approx(2e-3 / G * 1e3)
    assert "k" not in sd

"""The magnetometer's rows of the residual map: heading-free rest residuals with the calibration
refitted, within-rest scatter against the successive-difference noise, and the motions' samples
against the field carried by the gyro's attitude."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from imupipe.diagnosis.evaluate import Evaluation
from imupipe.diagnosis.magnetic import motion_rows, rest_rows, scatter_rows
from imupipe.diagnosis.residual_map import cells
from imupipe.models import TriadCalibration
from imupipe.observations import Rests

F, DIP, G = 50e-6, np.radians(70.0), 9.80665
S_MAG = np.array([[1.03, 0.02, -0.01], [0.0, 0.97, 0.015], [0.0, 0.0, 1.01]])
B_MAG = np.array([3e-6, -2e-6, 5e-6])
SIGMA = 3e-7  # T, one sample
N_SAMPLES = 200  # per rest


def _rests(rng, n=40, field_of_rest=None) -> Rests:
    R = Rotation.random(n, random_state=rng)
    f = R.inv().apply([0, 0, G])
    h_world = np.array([0.0, np.cos(DIP), -np.sin(DIP)])
    scale = np.ones(n) if field_of_rest is None else field_of_rest(np.arange(n))
    h = R.inv().apply(h_world) * (F * scale)[:, None]
    y = h @ S_MAG.T + B_MAG + rng.normal(0, SIGMA / np.sqrt(N_SAMPLES), (n, 3))
    a = f + rng.normal(0, 1e-3 / np.sqrt(N_SAMPLES), (n, 3))
    t0 = np.arange(n) * 10.0
    cov = {"mag": np.tile(np.eye(3) * SIGMA ** 2, (n, 1, 1)), "accel": np.tile(np.eye(3) * 1e-6, (n, 1, 1))}
    counts = {"mag": np.full(n, N_SAMPLES), "accel": np.full(n, N_SAMPLES)}
    return Rests(t0, t0 + 4.0, np.full(n, N_SAMPLES), {"mag": y, "accel": a}, cov, np.full(n, np.nan), counts)


def _mag_cal(rests: Rests) -> TriadCalibration:
    # a slightly wrong starting calibration: the rows judge the model after refitting it
    return TriadCalibration("mag", np.linalg.inv(S_MAG) @ (np.eye(3) + 0.01), B_MAG + 1e-6)


ACCEL = TriadCalibration("accel", np.eye(3))


def test_rest_rows_are_white_on_a_null_and_see_a_field_that_changes_between_places():
    rng = np.random.default_rng(1)
    rests = _rests(rng)
    rs, _ = rest_rows(rests, ACCEL, _mag_cal(rests))
    stat, dof = float(rs.r @ rs.r), float(rs.w.sum())
    assert len(rs.r) == 2 * len(rests) and dof < len(rs.r) - 10  # the refit's parameters are counted
    assert chi2.sf(stat, dof) > 1e-3 and chi2.cdf(stat, dof) > 1e-3
    moved = _rests(np.random.default_rng(1), field_of_rest=lambda i: np.where(i < 20, 1.0, 1.004))
    rs, _ = rest_rows(moved, ACCEL, _mag_cal(moved))
    flagged = [c for c in cells(rs) if c.p_value < 1e-6]
    assert any(c.variable == "time s" for c in flagged)


def test_within_rest_scatter_is_chi_square_on_a_quantised_null_with_thermal_drift():
    """A 5-min warm-up rest whose bias drifts as the calibration's k says, then 150 rests of 5 s;
    quantised white noise whose level differs between rests (0.25 to 1 LSB). The block's chi2/dof
    lies within 3 sd of 1 (a noise level pooled over rests, or the drift left in, puts it out)."""
    rng = np.random.default_rng(3)
    rate, k_mag = 100.0, np.array([2e-8, -2e-8, 1e-8])
    starts = np.r_[0.0, 305.0 + 7.0 * np.arange(150)]
    ends = np.r_[300.0, starts[1:] + 5.0]
    t = np.arange(0.0, ends[-1] + 1.0, 1 / rate)
    T = 25.0 + 6.0 * (1 - np.exp(-t / 200.0))
    sd = SIGMA * rng.uniform(0.5, 2.0, (len(starts), 1))
    level = sd[np.clip(np.searchsorted(starts, t, "right") - 1, 0, len(starts) - 1)]
    y = np.round((F + np.outer(T - 25.0, k_mag) + level * rng.normal(size=(len(t), 3))) / 1.5e-7) * 1.5e-7
    n = len(starts)
    rests = Rests(starts, ends, np.full(n, 500), {}, {}, np.full(n, np.nan))
    rs = scatter_rows(rests, t, y, k_mag, (t, T))
    stat, dof = float(rs.r @ rs.r), float(rs.w.sum())
    assert abs(stat / dof - 1) < 3 * np.sqrt(2 / dof)


def test_within_rest_scatter_sees_a_switched_current_but_not_white_noise_or_quantisation():
    rng = np.random.default_rng(2)
    rests = _rests(rng, n=12)
    t = np.arange(0, 120.0, 0.01)
    y = np.round((F + rng.normal(0, SIGMA, (len(t), 3))) / 1.5e-7) * 1.5e-7  # quantised white noise
    quiet = scatter_rows(rests, t, y)
    assert abs(float(quiet.r @ quiet.r) / quiet.w.sum() - 1) < 0.05
    y[:, 0] += 6e-7 * (np.mod(t, 1.0) < 0.5)  # a 1 Hz square wave of 0.6 uT on x
    loud = scatter_rows(rests, t, y)
    x = loud.axis == 0
    assert float(loud.r[x] @ loud.r[x]) / loud.w[x].sum() > 1.5


def test_motion_rows_are_white_on_a_null_and_see_a_field_sampled_late(fitted):
    """Inside the motions the calibrated field follows the gyro's attitude: white at the true
    calibration, and far from white when the magnetometer's clock is 10 ms late."""
    _, out, truth, _, rests, _, lin = fitted
    ev = Evaluation(lin, np.eye(3), None)  # the accelerometer's S is lower-triangular: no gauge rotation
    args = (out.raw["mag"], truth.calibration["mag"], (out.t, out.temperature))
    rs = motion_rows(ev, rests, out.t, *args)
    assert set(rs.regime) == {"motion"} and len(rs.r) > 3000
    dof = rs.w.sum()
    assert abs((rs.r ** 2).sum() / dof - 1) < 3 * np.sqrt(2 / dof)
    late = motion_rows(ev, rests, out.t - 0.01, *args)
    assert chi2.sf((late.r ** 2).sum(), late.w.sum()) < 1e-9


def test_motion_rows_formed_by_chunks_of_samples_are_the_same_bits(fitted, monkeypatch):
    """The motions' rotations and whiteners are formed ``ROW_CHUNK`` samples at a time (twice: the
    per-motion fields' sums, then the rows): chunks that split motions give the same rows."""
    from imupipe.diagnosis import magnetic

    _, out, truth, _, rests, _, lin = fitted
    ev = Evaluation(lin, np.eye(3), None)
    args = (out.t, out.raw["mag"], truth.calibration["mag"], (out.t, out.temperature))
    whole = motion_rows(ev, rests, *args)
    monkeypatch.setattr(magnetic, "ROW_CHUNK", 997)
    chunked = motion_rows(ev, rests, *args)
    assert len(whole.r) > 3 * 997
    for a, b in ((whole.r, chunked.r), (whole.w, chunked.w), (whole.t, chunked.t)):
        np.testing.assert_array_equal(a, b)

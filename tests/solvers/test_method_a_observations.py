"""The observation types both methods' solvers share: Arrow round trips and the forward Jacobian."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from imupipe import schemas
from imupipe.models import TriadCalibration
from imupipe.observations import Rests, Turns, forward_jacobian


def make_rests(n: int = 5, mag: bool = True) -> Rests:
    rng = np.random.default_rng(0)
    sensors = ("accel", "gyro", "mag") if mag else ("accel", "gyro")
    A = rng.normal(size=(n, 3, 3))
    return Rests(np.arange(n) * 10.0, np.arange(n) * 10.0 + 5, np.full(n, 500),
                 {s: rng.normal(size=(n, 3)) for s in sensors},
                 {s: A @ A.transpose(0, 2, 1) for s in sensors},
                 np.linspace(30, 35, n), {s: np.full(n, 500 + i) for i, s in enumerate(sensors)},
                 1_000_000_000)


def test_rests_round_trip_exactly():
    r = make_rests()
    t = r.to_table()
    schemas.check(t, "rests")
    back = Rests.from_table(t)
    assert back.t0_ns == r.t0_ns and back.sensors == ("accel", "gyro", "mag")
    for s in r.sensors:
        assert np.array_equal(back.mean[s], r.mean[s]) and np.array_equal(back.cov[s], r.cov[s])
        assert np.array_equal(back.counts[s], r.counts[s])
    assert np.allclose(back.cov_of_mean("gyro"), r.cov["gyro"] / 501)


def test_rests_without_mag_have_no_mag():
    back = Rests.from_table(make_rests(mag=False).to_table())
    assert not back.has("mag")


def test_turns_take_the_gyro_samples_between_rests():
    t_ns = 1_000_000_000 + np.arange(0, 100) * 10_000_000  # 100 Hz for 1 s
    gyro = schemas.stamp(pa.table({"t_ns": t_ns, "x": np.arange(100.0), "y": np.zeros(100),
                                   "z": np.zeros(100)}), "gyro")
    turns = schemas.stamp(pa.table({
        "index": [0], "rest_before": [0], "rest_after": [1], "t_start_ns": [t_ns[10]],
        "t_end_ns": [t_ns[19]], "duration_s": [0.09], "n_samples": [10], "angle_deg": [0.0]}),
        "turns", {"imupipe.t0_ns": str(t_ns[0])})
    tr = Turns.from_tables(turns, gyro)
    assert np.array_equal(tr.gyro[0][:, 0], np.arange(10.0, 20.0))
    assert np.allclose(tr.t[0], np.arange(10, 20) * 0.01)


def test_forward_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    cal = TriadCalibration("accel", np.eye(3) + 0.05 * rng.normal(size=(3, 3)), rng.normal(size=3),
                           rng.normal(size=3) * 1e-3)
    x, T = rng.normal(size=(4, 3)) * 9.8, 30 + 5 * rng.normal(size=4)
    p = np.concatenate([cal.M.ravel(), cal.b0, cal.k])

    def predict(q):
        return TriadCalibration("accel", q[:9].reshape(3, 3), q[9:12], q[12:]).predict(x, T)

    h = 1e-7
    numeric = np.stack([(predict(p + h * e) - predict(p)) / h for e in np.eye(15)], axis=-1)
    assert np.abs(forward_jacobian(cal, x, T) - numeric).max() < 1e-5

"""Simulated recordings with their true segments, as the forward model's inputs."""

from __future__ import annotations

import numpy as np

from imupipe.diagnosis.forward import JointModel, MotionAccel, Noise, Start
from imupipe.observations import Rests, Turns
from imupipe.sim.api import simulate_arrays

G = 9.80665


def lower_triad(rng, scale=0.02, mis=0.01):
    S = np.eye(3) + np.diag(rng.uniform(-scale, scale, 3)) + np.tril(rng.normal(0, mis, (3, 3)), -1)
    return S


def noise_free_imu(seed: int) -> dict:
    """Scale, misalignment, bias and k errors; no noise, LSB, range, turn-on bias or walk.
    The accelerometer's S is lower-triangular (the joint model's gauge)."""
    rng = np.random.default_rng(seed)
    Sg = np.eye(3) + np.diag(rng.uniform(-0.02, 0.02, 3)) + (1 - np.eye(3)) * rng.normal(0, 0.01, (3, 3))
    return {
        "accel": {"S": lower_triad(rng).tolist(), "b0": rng.uniform(-0.3, 0.3, 3).tolist(),
                  "k": rng.uniform(-2e-3, 2e-3, 3).tolist()},
        "gyro": {"S": Sg.tolist(), "b0": rng.uniform(-0.02, 0.02, 3).tolist(),
                 "k": rng.uniform(-1e-4, 1e-4, 3).tolist()},
        "thermal": {"readout_quantum_C": 0.0},
    }


def rests_from_truth(out, truth, sigma_a=5e-3, sigma_g=3.5e-4):
    """Rests over the true rest segments (noise weights given, since the data may be noise-free)
    and the turns between consecutive rests; ``(rests, turns, t)``."""
    t = out.t
    segs = truth.rests
    n = len(segs)
    mean, cov, counts = {}, {}, {}
    idx = [(np.searchsorted(t, a, "left"), np.searchsorted(t, b, "right")) for a, b in segs]
    for s, sd in (("accel", sigma_a), ("gyro", sigma_g)):
        mean[s] = np.array([out.raw[s][i0:i1].mean(0) for i0, i1 in idx])
        cov[s] = np.tile(np.eye(3) * sd**2, (n, 1, 1))
        counts[s] = np.array([i1 - i0 for i0, i1 in idx])
    T = np.array([out.temperature[i0:i1].mean() for i0, i1 in idx])
    ts, te = np.array([t[i0] for i0, _ in idx]), np.array([t[i1 - 1] for _, i1 in idx])
    rests = Rests(ts, te, counts["accel"], mean, cov, T, counts)
    tt, ww = [], []
    for p in range(n - 1):
        i0, i1 = np.searchsorted(t, te[p], "left"), np.searchsorted(t, ts[p + 1], "right")
        tt.append(t[i0:i1])
        ww.append(out.raw["gyro"][i0:i1])
    turns = Turns(np.arange(n - 1), np.arange(1, n), tuple(tt), tuple(ww))
    return rests, turns


def small_sphere_rig(seed: int, imu: dict, **kw):
    """Rests at random attitudes joined by single turns (no two motions back to back)."""
    params = dict(warmup_s=0.0, n_positions=12, n_turns=12, rest_s=2.0, turn_s=3.0, max_turn_deg=30.0,
                  reference_rest_s=2.0)
    params.update(kw)
    return simulate_arrays("sphere_rig", None, seed, imu=imu, env={"gravity_m_s2": G}, **params)


def small_gimbal(seed: int, imu: dict, **kw):
    params = dict(grid_deg=60.0, rest_s=2.0, step_s=1.5, n_rotations=6, rotation_s=2.0)
    params.update(kw)
    return simulate_arrays("gimbal", None, seed, imu=imu, env={"gravity_m_s2": G}, **params)


def joint_model(out, truth, fit_k: bool = True):
    """The per-sample model of a simulated session, started at its true calibration, with its rests,
    turns and accelerometer samples (tests of the diagnosis)."""
    rests, turns = rests_from_truth(out, truth)
    cal = truth.calibration
    start = Start(np.linalg.inv(cal["accel"].M), cal["accel"].b0, cal["gyro"].M, cal["gyro"].b0,
                  cal["accel"].k, cal["gyro"].k)
    noise = Noise(np.eye(3) * 5e-3**2, np.eye(3) * 3.5e-4**2, np.full(3, 1e-9), np.full(3, 1e-10))
    acc = MotionAccel.select(out.t, out.raw["accel"], rests, turns)
    return JointModel(rests, turns, G, start, noise, fit_k=fit_k, accel=acc,
                      temperature=(out.t, out.temperature)), rests, turns

"""Synthetic rests and turns with known errors, for the method-B solver tests.

Observation level (no segmentation in the loop): each rest gives exact-noise
means, each turn raw gyro samples of a smoothly varying body rate whose true
rotation is integrated on a grid 16x finer than the samples. Seeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imupipe.observations import Rests, Turns
from imupipe.rotations import compose, quat_exp, quat_to_matrix, random_rotation

G = 9.80665

S_ACCEL = np.array([[0.985, 0.0, 0.0], [0.0042, 1.013, 0.0], [-0.0031, 0.0055, 0.992]])
B_ACCEL = np.array([0.12, -0.08, 0.21])  # m/s^2
S_GYRO = np.array([[1.021, 0.0062, -0.0041], [-0.0053, 0.978, 0.0087], [0.0035, -0.0072, 1.004]])
B_GYRO = np.array([0.0031, -0.0017, 0.0009])  # rad/s


@dataclass(frozen=True)
class Session:
    rests: Rests
    turns: Turns
    S_accel: np.ndarray
    b_accel: np.ndarray
    S_gyro: np.ndarray
    b_gyro: np.ndarray
    sigma_accel: float
    sigma_gyro: float
    gravity_body: np.ndarray  # (n, 3) true unit gravity at each rest, instrument frame


def make_session(seed: int, n_rests: int = 60, rate_hz: float = 100.0, rest_s: float = 4.0,
                 turn_s: float = 2.0, sigma_accel: float = 0.02, sigma_gyro: float = 0.003,
                 speed_dps: float = 90.0, S_accel: np.ndarray = S_ACCEL,
                 b_accel: np.ndarray = B_ACCEL, S_gyro: np.ndarray = S_GYRO,
                 b_gyro: np.ndarray = B_GYRO, k_accel: np.ndarray | None = None,
                 k_gyro: np.ndarray | None = None) -> Session:
    """Rests at random attitudes joined by turns of varying axis (gimbal-like).

    ``sigma_*``: white noise of one sample (m/s^2, rad/s). Body rate during a
    turn: ``sin^2`` envelope times ``w0 + w1 sin(2 pi t / turn_s)``. With
    ``k_*`` (per degC) the die warms from 22 degC by 20 degC (tau 600 s) and the
    biases follow ``k (T - 25)``; rests then carry temperatures.
    """
    warm = k_accel is not None or k_gyro is not None
    k_accel = np.zeros(3) if k_accel is None else k_accel
    k_gyro = np.zeros(3) if k_gyro is None else k_gyro

    def temp(t: np.ndarray) -> np.ndarray:
        return 22.0 + 20.0 * (1 - np.exp(-np.asarray(t) / 600.0))

    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    n_rest = round(rest_s * rate_hz)
    k = round(turn_s * rate_hz)
    sub = 16
    C = random_rotation(rng)  # body -> world
    g_world = np.array([0.0, 0.0, G])  # specific force at rest points up
    up, t_s, t_e = [], [], []
    turn_t, turn_w, t = [], [], 0.0
    speed = np.radians(speed_dps)
    for i in range(n_rests):
        up.append(C.T @ g_world / G)
        t_s.append(t)
        t += (n_rest - 1) * dt
        t_e.append(t)
        if i == n_rests - 1:
            break
        w0, w1 = rng.normal(size=3), rng.normal(size=3)
        w0 *= speed / np.linalg.norm(w0)
        w1 *= 0.5 * speed / np.linalg.norm(w1)
        # Samples at t + (j+1) dt, j = 0..k-1; each stands for [t_j - dt/2, t_j + dt/2].
        tj = (np.arange(k) + 1) * dt
        fine = (np.arange(k * sub) + 0.5) * dt / sub + 0.5 * dt

        def body_rate(tau: np.ndarray, w0: np.ndarray = w0, w1: np.ndarray = w1) -> np.ndarray:
            env = np.sin(np.pi * np.clip(tau, 0, turn_s + dt) / (turn_s + dt)) ** 2
            return env[:, None] * (w0 + np.outer(np.sin(2 * np.pi * tau / turn_s), w1))

        q = quat_exp(body_rate(fine) * (dt / sub))[None]
        C = C @ quat_to_matrix(compose(q))[0]
        raw = body_rate(tj) @ S_gyro.T + b_gyro + rng.normal(size=(k, 3)) * sigma_gyro
        raw += np.outer(temp(t + tj) - 25.0, k_gyro)
        turn_t.append(t + tj)
        turn_w.append(raw)
        t += (k + 1) * dt
    up = np.array(up)
    n = len(up)
    counts = np.full(n, n_rest)
    T = temp(0.5 * (np.array(t_s) + np.array(t_e)))
    acc_mean = (G * up) @ S_accel.T + b_accel + rng.normal(size=(n, 3)) * sigma_accel / np.sqrt(n_rest)
    gyr_mean = b_gyro + rng.normal(size=(n, 3)) * sigma_gyro / np.sqrt(n_rest)
    acc_mean += np.outer(T - 25.0, k_accel)
    gyr_mean += np.outer(T - 25.0, k_gyro)
    rests = Rests(
        np.array(t_s), np.array(t_e), counts,
        {"accel": acc_mean, "gyro": gyr_mean},
        {"accel": np.tile(np.eye(3) * sigma_accel**2, (n, 1, 1)),
         "gyro": np.tile(np.eye(3) * sigma_gyro**2, (n, 1, 1))},
        T if warm else np.full(n, np.nan), {"accel": counts, "gyro": counts},
    )
    turns = Turns(np.arange(n - 1), np.arange(1, n), tuple(turn_t), tuple(turn_w))
    return Session(rests, turns, S_accel, b_accel, S_gyro, b_gyro, sigma_accel, sigma_gyro, up)



def session_tables(s: Session) -> dict:
    """``rests`` and ``turns`` tables and a ``gyro`` table holding the turns' samples."""
    from dataclasses import replace

    import pyarrow as pa

    from imupipe import schemas

    t0_ns = 1_000_000_000
    rests = replace(s.rests, t0_ns=t0_ns).to_table()
    t = np.concatenate(s.turns.t)
    w = np.concatenate(s.turns.gyro)
    gyro = schemas.stamp(pa.table({"t_ns": t0_ns + np.round(t * 1e9).astype(np.int64),
                                   "x": w[:, 0], "y": w[:, 1], "z": w[:, 2]}), "gyro")
    starts = np.array([ti[0] for ti in s.turns.t])
    ends = np.array([ti[-1] for ti in s.turns.t])
    turns = pa.table({
        "index": np.arange(len(starts), dtype=np.int64),
        "rest_before": s.turns.before.astype(np.int64), "rest_after": s.turns.after.astype(np.int64),
        "t_start_ns": t0_ns + np.round(starts * 1e9).astype(np.int64),
        "t_end_ns": t0_ns + np.round(ends * 1e9).astype(np.int64),
        "duration_s": ends - starts, "n_samples": np.array([len(ti) for ti in s.turns.t]),
        "angle_deg": np.zeros(len(starts)),
    })
    turns = schemas.stamp(turns, "turns", {"imupipe.t0_ns": str(t0_ns)})
    return {"rests": rests, "turns": turns, "gyro": gyro}

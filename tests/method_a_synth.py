"""Minimal synthetic rests and turns with known errors, for the method A solver tests.

Kept independent of ``imupipe.sim`` so that the solvers are tested against a
generator written from the model equations alone.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from imupipe.observations import GyroObservations, Turns

G = 9.80665
# Monte Carlo truth of the paper (Tables 1-3): forward matrix and bias in g
S_ACC = np.array([[0.947, 0.059, -0.045], [-0.068, 1.046, 0.058], [0.06, -0.047, 1.017]])
B_ACC = np.array([0.01, -0.05, 0.02]) * G
S_GYR = np.array([[1.02, 0.004, -0.003], [0.006, 0.985, 0.002], [-0.005, 0.003, 1.01]])
B_GYR = np.array([0.01, -0.02, 0.005])


def unit_sphere(n: int, rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def random_walk_attitudes(n: int, max_deg: float, rng: np.random.Generator) -> list[Rotation]:
    """Body-to-world attitudes of ``n`` rests, each a turn of <= max_deg from the last."""
    att = [Rotation.random(random_state=rng.integers(1 << 31))]
    for _ in range(n - 1):
        axis = unit_sphere(1, rng)[0]
        att.append(att[-1] * Rotation.from_rotvec(axis * np.radians(rng.uniform(0.5, 1) * max_deg)))
    return att


def gyro_session(n_rests: int, max_deg: float, rng: np.random.Generator, *, rate_hz: float = 100.0,
                 turn_s: float = 3.0, noise: float = 0.0, coning: float = 0.0,
                 S: np.ndarray = S_GYR, b: np.ndarray = B_GYR) -> tuple[GyroObservations, list]:
    """Rests joined by turns about random axes; raw gyro ``S w + b (+ noise)``.

    ``coning``: amplitude (rad/s) of a rate component orthogonal to the turn axis
    that integrates to zero, so the motion is not about a fixed axis.
    Returns observations with the TRUE unit gravity at each rest, and the attitudes.
    """
    att = random_walk_attitudes(n_rests, max_deg, rng)
    up = np.array([0.0, 1.0, 0.0])
    gravity = np.array([a.inv().apply(up) for a in att])
    ts, ws = [], []
    for j in range(n_rests - 1):
        rel = (att[j].inv() * att[j + 1]).as_rotvec()  # body rotation in the body frame
        k = int(turn_s * rate_hz)
        t = j * 10.0 + np.arange(k) / rate_hz
        w = np.tile(rel / turn_s, (k, 1))
        if coning:
            perp = np.cross(rel, unit_sphere(1, rng)[0])
            perp /= np.linalg.norm(perp)
            w += coning * np.outer(np.sin(2 * np.pi * np.arange(k) / k), perp)
        # re-integrate the commanded rates so the true end attitude matches them exactly
        q = att[j]
        for wk in w:
            q = q * Rotation.from_rotvec(wk / rate_hz)
        att[j + 1] = q
        gravity[j + 1] = q.inv().apply(up)
        raw = w @ S.T + b + noise * rng.normal(size=w.shape)
        ts.append(t)
        ws.append(raw)
    turns = Turns(np.arange(n_rests - 1), np.arange(1, n_rests), tuple(ts), tuple(ws))
    bias = np.tile(b, (n_rests, 1))
    obs = GyroObservations(gravity, bias, np.tile(np.eye(3) * 1e-12, (n_rests, 1, 1)), turns)
    return obs, att

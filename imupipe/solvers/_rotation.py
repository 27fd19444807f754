"""Finite rotations shared by the gyroscope solver and the turn validation.

Quaternions are (w, x, y, z), Hamilton product; a body-rate integration gives
the body's rotation from the start of a motion to its end, in the body frame
at the start.
"""

from __future__ import annotations

import numpy as np


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = p
    w2, x2, y2, z2 = q
    return np.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


def quat_exp(phi: np.ndarray) -> np.ndarray:
    """Quaternion of rotation vector ``phi`` (3,) rad."""
    a = float(np.linalg.norm(phi))
    if a < 1e-12:
        return np.array([1.0, *(0.5 * phi)])
    return np.array([np.cos(a / 2), *(np.sin(a / 2) * phi / a)])


def step_times(t: np.ndarray) -> np.ndarray:
    """(k,) integration step of each sample, s: the time to the next sample (zero-order hold).

    The last sample gets the median step; tolerates irregular or bursty stamps.
    """
    if len(t) < 2:
        return np.zeros(len(t))
    dt = np.diff(t)
    return np.append(dt, np.median(dt))


def integrate_rotation(t: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Quaternion (4,) of the rotation of body rates ``w`` (k, 3) rad/s at times ``t`` (k,) s."""
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for dt, wk in zip(step_times(t), w, strict=True):
        q = quat_mul(q, quat_exp(wk * dt))
    return q / np.linalg.norm(q)


def gibbs(q: np.ndarray) -> np.ndarray:
    """Half finite-rotation (Gibbs) vector ``e tan(chi/2)`` of quaternion ``q``."""
    return q[1:] / q[0]


def rotation_vector(q: np.ndarray) -> np.ndarray:
    """Rotation vector ``e chi`` (3,) rad of quaternion ``q``."""
    q = q if q[0] >= 0 else -q
    s = np.linalg.norm(q[1:])
    if s < 1e-15:
        return 2 * q[1:]
    return q[1:] / s * 2 * np.arctan2(s, q[0])


def nearest_rotation(A: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to ``A`` (3, 3) in Frobenius norm (polar factor)."""
    U, _, Vt = np.linalg.svd(A)
    d = np.sign(np.linalg.det(U @ Vt))
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def frame_from_up_vectors(y_up: np.ndarray, x_up: np.ndarray | None) -> np.ndarray:
    """Rotation R (3, 3) whose rows are the instrument axes in the current frame.

    ``y_up``: the vector measured with instrument Y up; ``x_up``: with X up
    (its part orthogonal to ``y_up`` fixes the heading, eqs. 18-19). Without
    ``x_up``, the heading is the one that keeps the current x axis in the X-Y
    plane (smallest turn).
    """
    ey = y_up / np.linalg.norm(y_up)
    ref = x_up if x_up is not None else np.array([1.0, 0.0, 0.0])
    ex = ref - ey * (ey @ ref)
    if np.linalg.norm(ex) < 1e-6:
        ex = np.array([0.0, 0.0, 1.0]) - ey * ey[2]
    ex /= np.linalg.norm(ex)
    ez = np.cross(ex, ey)
    return np.vstack([ex, ey, ez])


def integrate_rotations(ts: list[np.ndarray], ws: list[np.ndarray]) -> np.ndarray:
    """Quaternions (m, 4) of m motions at once: ``integrate_rotation`` vectorised over motions.

    ``ts``: m arrays (k_i,) s; ``ws``: m arrays (k_i, 3) rad/s. Shorter motions are
    padded with zero steps.
    """
    m = len(ts)
    kmax = max((len(t) for t in ts), default=0)
    phi = np.zeros((m, kmax, 3))
    for i, (t, w) in enumerate(zip(ts, ws, strict=True)):
        phi[i, : len(t)] = w * step_times(t)[:, None]
    q = np.zeros((m, 4))
    q[:, 0] = 1.0
    for k in range(kmax):
        p = phi[:, k]
        a = np.linalg.norm(p, axis=1)
        half = 0.5 * a
        s = np.where(a > 1e-12, np.sin(half) / np.where(a > 1e-12, a, 1.0), 0.5)
        dq = np.column_stack([np.cos(half), p * s[:, None]])
        w1, x1, y1, z1 = q.T
        w2, x2, y2, z2 = dq.T
        q = np.column_stack([
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rotation_vectors(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (m, 3) rad of quaternions (m, 4)."""
    return np.array([rotation_vector(qi) for qi in q]).reshape(-1, 3)


def quat_to_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (m, 3, 3) of quaternions (m, 4) (w, x, y, z)."""
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def carry_gravity(q: np.ndarray, g0: np.ndarray) -> np.ndarray:
    """(m, 3) world-fixed vectors ``g0`` (m, 3) seen in the body after it turned by ``q`` (m, 4)."""
    return np.einsum("mji,mj->mi", quat_to_matrices(q), g0)

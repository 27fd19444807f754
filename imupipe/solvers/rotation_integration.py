"""Exact rotation over a turn from gyro samples, vectorised over all turns.

Each sample ``k`` is taken as a constant rate over its interval ``dt_k``, so its
rotation is ``exp(omega_k dt_k)`` exactly (no small-angle approximation); the
turn's rotation is the ordered product of those. Turns are padded to one length
with identity rotations and the products are formed by a log-depth pairwise
scan, so the cost of a turn set is ``log2(k_max)`` numpy calls, never a Python
loop per sample.

Quaternions are ``(..., 4)`` arrays ``(w, x, y, z)``, Hamilton convention. The
turn quaternion ``q`` maps vectors in the body frame at the END of the turn to
the body frame at its START: ``v_start = R(q) v_end``. Gravity, fixed in the
world, therefore obeys ``g_end = R(q)^T g_start`` (Chikrin & Golousov, Eq. (2.16)).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

# Below this rotation angle (rad) exp uses its Taylor series (relative error < 1e-16).
_SMALL_ANGLE = 1e-4


def sample_intervals(t: np.ndarray) -> np.ndarray:
    """(k,) s: the time each sample stands for (centred differences of ``t`` (k,) s)."""
    t = np.asarray(t, dtype=float)
    if len(t) < 2:
        return np.zeros(len(t))
    d = np.diff(t)
    dt = np.empty(len(t))
    dt[1:-1] = 0.5 * (d[:-1] + d[1:])
    dt[0], dt[-1] = d[0], d[-1]
    return dt


def pad_turns(t: Sequence[np.ndarray], rate: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Stack ragged turns: rates (m, k_max, 3) rad/s and intervals (m, k_max) s, zero-padded.

    ``t``: m arrays (k_i,) s; ``rate``: m arrays (k_i, 3) rad/s. Padded samples
    have ``dt = 0`` and so rotate by nothing.
    """
    m = len(rate)
    k_max = max((len(w) for w in rate), default=0)
    w_pad = np.zeros((m, max(k_max, 1), 3))
    dt_pad = np.zeros((m, max(k_max, 1)))
    for i, (ti, wi) in enumerate(zip(t, rate, strict=True)):
        w_pad[i, : len(wi)] = wi
        dt_pad[i, : len(wi)] = sample_intervals(ti)
    return w_pad, dt_pad


def quat_exp(phi: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) of rotation vectors ``phi`` (..., 3) rad."""
    theta2 = np.einsum("...i,...i->...", phi, phi)
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    # sin(theta/2)/theta and cos(theta/2), with their series near zero.
    s = np.where(small, 0.5 - theta2 / 48.0, np.sin(0.5 * safe) / safe)
    c = np.where(small, 1.0 - theta2 / 8.0, np.cos(0.5 * safe))
    return np.concatenate([c[..., None], s[..., None] * phi], axis=-1)


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p * q`` of quaternion arrays (..., 4)."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ], axis=-1)


def compose(q: np.ndarray) -> np.ndarray:
    """Ordered products ``q[:, 0] * q[:, 1] * ... * q[:, k-1]``: (m, k, 4) -> (m, 4).

    Log-depth pairwise reduction: adjacent pairs are multiplied in order, which
    associativity makes equal to the left-to-right product.
    """
    while q.shape[1] > 1:
        if q.shape[1] % 2:
            identity = np.zeros((q.shape[0], 1, 4))
            identity[..., 0] = 1.0
            q = np.concatenate([q, identity], axis=1)
        q = quat_mul(q[:, 0::2], q[:, 1::2])
    return q[:, 0]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) (normalised first)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-2)


def turn_rotations(rate: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Rotation matrices (m, 3, 3) of padded turns: ``rate`` (m, k, 3) rad/s, ``dt`` (m, k) s.

    ``rate`` is already corrected (bias removed, scale/misalignment applied).
    """
    return quat_to_matrix(compose(quat_exp(rate * dt[..., None])))


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (...,) rad of rotation matrices (..., 3, 3)."""
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arccos(np.clip(c, -1.0, 1.0))

"""Rotation matrices: exponential map, axis construction, random rotations.

Every rotation is a ``(3, 3)`` or stacked ``(n, 3, 3)`` proper orthogonal
matrix. ``R`` of the simulator is body-to-world: ``v_world = R @ v_body``.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x``: (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], -1),
        np.stack([v[..., 2], z, -v[..., 0]], -1),
        np.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def exp_so3(axis: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rodrigues' formula: rotation by ``angle`` (rad, scalar or (n,)) about unit ``axis`` (3,)."""
    axis = np.asarray(axis, dtype=float)
    angle = np.asarray(angle, dtype=float)
    K = skew(axis)
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """Rotation vector (..., 3) (rad) to matrix (..., 3, 3)."""
    rv = np.asarray(rv, dtype=float)
    angle = np.linalg.norm(rv, axis=-1)
    safe = np.where(angle > 0, angle, 1.0)
    axis = rv / safe[..., None]
    K = skew(axis)
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Matrix (3, 3) to rotation vector (3,) (rad), angle in [0, pi]; robust near a half turn."""
    R = np.asarray(R, dtype=float)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-8:
        return 0.5 * w
    if angle < np.pi - 1e-3:
        return w * angle / (2.0 * np.sin(angle))
    B = (R + np.eye(3)) / 2.0  # = a a^T at a half turn
    j = int(np.argmax(np.diag(B)))
    axis = B[:, j] / np.sqrt(B[j, j])
    if axis @ w < 0:
        axis = -axis
    return axis / np.linalg.norm(axis) * angle


def angle_between(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation ``R1.T @ R2``; (...,). Accurate for small angles too."""
    Rd = np.swapaxes(R1, -1, -2) @ R2
    w = np.stack([Rd[..., 2, 1] - Rd[..., 1, 2], Rd[..., 0, 2] - Rd[..., 2, 0], Rd[..., 1, 0] - Rd[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(w, axis=-1), 0.5 * (np.trace(Rd, axis1=-2, axis2=-1) - 1.0))


def align(body_vec: np.ndarray, world_vec: np.ndarray, heading_rad: float = 0.0) -> np.ndarray:
    """A body-to-world rotation taking unit ``body_vec`` to unit ``world_vec``, then turned by
    ``heading_rad`` about ``world_vec`` (the free angle)."""
    a = np.asarray(body_vec, float) / np.linalg.norm(body_vec)
    b = np.asarray(world_vec, float) / np.linalg.norm(world_vec)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-12:
        if c > 0:
            R = np.eye(3)
        else:  # half turn about any axis normal to a
            n = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
            R = exp_so3(n / np.linalg.norm(n), np.pi)
    else:
        R = exp_so3(v / s, np.arctan2(s, c))
    return exp_so3(b, heading_rad) @ R


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation uniformly distributed over SO(3) (Haar measure), (3, 3)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def random_unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` unit vectors uniform on the sphere, (n, 3)."""
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)

"""Finite rotations: matrices, quaternions, rotation vectors, body rates integrated exactly.

Rotation matrices are ``(3, 3)`` or stacked ``(..., 3, 3)``; quaternions are
``(..., 4)`` arrays ``(w, x, y, z)``, Hamilton convention. The simulator's ``R``
is body-to-world: ``v_world = R @ v_body``.

Body rates over a motion (a turn between two rests) integrate to the rotation
``q`` that maps vectors in the body frame at the END of the motion to the body
frame at its START: ``v_start = R(q) v_end``. A world-fixed vector such as
gravity therefore obeys ``g_end = R(q)^T g_start`` (``carry``; Chikrin &
Golousov, Eq. (2.16)). Each sample is a constant rate over its interval, so its
rotation is ``exp(omega dt)`` exactly; motions are padded to one length with
zero intervals and the ordered products formed by a log-depth pairwise scan
(``compose``): ``log2(k_max)`` numpy calls for a whole set, no loop per sample.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

# Below this rotation angle (rad) exp uses its Taylor series (relative error < 1e-16).
_SMALL_ANGLE = 1e-4


# --------------------------------------------------------------------------- matrices


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x``: (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def exp_so3(axis: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rodrigues' formula: rotation by ``angle`` (rad, scalar or (n,)) about unit ``axis`` (3,)."""
    axis = np.asarray(axis, dtype=float)
    angle = np.asarray(angle, dtype=float)
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


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (...,) rad of rotation matrices (..., 3, 3); accurate for small angles too."""
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(w, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0))


def angle_between(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Angle (...,) rad of the rotation ``R1.T @ R2``."""
    return rotation_angle(np.swapaxes(R1, -1, -2) @ R2)


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
    return quat_to_matrix(rng.normal(size=4))


# --------------------------------------------------------------------------- quaternions


def _half_angle(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sin(theta/2)/theta`` and ``cos(theta/2)`` of rotation vectors ``phi`` (..., 3), with
    their series near zero; the sine and cosine only where needed (padded turns are zero
    rotations)."""
    theta2 = np.einsum("...i,...i->...", phi, phi)
    theta = np.sqrt(theta2)
    s, c = np.asarray(0.5 - theta2 / 48.0), np.asarray(1.0 - theta2 / 8.0)
    big = theta >= _SMALL_ANGLE
    t = theta[big]
    s[big] = np.sin(0.5 * t) / t
    c[big] = np.cos(0.5 * t)
    return s, c


def quat_exp(phi: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) of rotation vectors ``phi`` (..., 3) rad."""
    s, c = _half_angle(phi)
    q = np.empty((*phi.shape[:-1], 4), np.result_type(s, phi))
    q[..., 0] = c
    np.multiply(s[..., None], phi, out=q[..., 1:])
    return q


def _quat_exp_first(phi: np.ndarray) -> np.ndarray:
    """``quat_exp`` with the components first: (4, ...) of ``phi`` (..., 3)."""
    s, c = _half_angle(phi)
    q = np.empty((4, *phi.shape[:-1]))
    q[0] = c
    np.multiply(s, np.moveaxis(phi, -1, 0), out=q[1:])
    return q


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p * q`` of quaternion arrays (..., 4): ``quat_mul_into`` on their
    components (the scans multiply component-first arrays with it directly)."""
    p, q = np.broadcast_arrays(p, q)
    out = np.empty((4, *p.shape[:-1]))
    quat_mul_into(np.moveaxis(p, -1, 0), np.moveaxis(q, -1, 0), out, np.empty(p.shape[:-1]))
    return np.moveaxis(out, 0, -1)


# the Hamilton product's terms per component of p * q: (p's, q's, sign)
_HAMILTON = (((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
             ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
             ((0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)),
             ((0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)))


def quat_mul_into(p: np.ndarray, q: np.ndarray, out: np.ndarray, scratch: np.ndarray) -> np.ndarray:
    """The Hamilton product of component-first quaternions ``p``, ``q`` (4, ...) into ``out``
    (4, ...; not ``p`` or ``q``), ``scratch`` (...) its one temporary: whole components and no
    allocation (2.6x faster in a scan than products of (n, 4) arrays)."""
    for o, terms in zip(out, _HAMILTON, strict=True):
        (i, j, _), *rest = terms
        np.multiply(p[i], q[j], out=o)
        for i, j, sign in rest:
            np.multiply(p[i], q[j], out=scratch)
            (np.add if sign > 0 else np.subtract)(o, scratch, out=o)
    return out


def compose(q: np.ndarray) -> np.ndarray:
    """Ordered products ``q[:, 0] * q[:, 1] * ... * q[:, k-1]``: (m, k, 4) -> (m, 4).

    Log-depth pairwise reduction: adjacent pairs are multiplied in order, which
    associativity makes equal to the left-to-right product.
    """
    return _compose_first(np.moveaxis(q, -1, 0)).T


def _compose_first(q: np.ndarray) -> np.ndarray:
    """``compose`` of component-first quaternions (4, m, k) -> (4, m): each level's pairs are
    strided views multiplied into one new array (no transposed copies: 1.1-1.3x faster)."""
    while q.shape[-1] > 1:
        if q.shape[-1] % 2:
            identity = np.zeros((*q.shape[:-1], 1))
            identity[0] = 1.0
            q = np.concatenate([q, identity], axis=-1)
        out = np.empty((*q.shape[:-1], q.shape[-1] // 2))
        quat_mul_into(q[..., 0::2], q[..., 1::2], out, np.empty(out.shape[1:]))
        q = out
    return q[..., 0]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) (normalised first)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))  # each entry written in place (no stacked copies)
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return R


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) rad, angle in [0, pi], of unit quaternions (..., 4)."""
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    tiny = s < 1e-15
    return np.where(tiny, 2 * q[..., 1:],
                    q[..., 1:] / np.where(tiny, 1.0, s) * 2 * np.arctan2(s, q[..., :1]))


# --------------------------------------------------------------------------- body rates


def hold_intervals(t: np.ndarray) -> np.ndarray:
    """(k,) s: each sample held until the next one (zero-order hold) of ``t`` (k,) s.

    The last sample gets the median step; tolerates irregular or bursty stamps.
    """
    t = np.asarray(t, dtype=float)
    if len(t) < 2:
        return np.zeros(len(t))
    dt = np.diff(t)
    return np.append(dt, np.median(dt))


def centred_intervals(t: np.ndarray) -> np.ndarray:
    """(k,) s: the time each sample stands for (centred differences of ``t`` (k,) s)."""
    t = np.asarray(t, dtype=float)
    if len(t) < 2:
        return np.zeros(len(t))
    d = np.diff(t)
    dt = np.empty(len(t))
    dt[1:-1] = 0.5 * (d[:-1] + d[1:])
    dt[0], dt[-1] = d[0], d[-1]
    return dt


def pad_turns(t: Sequence[np.ndarray], rate: Sequence[np.ndarray],
              intervals: Callable[[np.ndarray], np.ndarray] = centred_intervals,
              ) -> tuple[np.ndarray, np.ndarray]:
    """Stack ragged turns: rates (m, k_max, 3) rad/s and intervals (m, k_max) s, zero-padded.

    ``t``: m arrays (k_i,) s; ``rate``: m arrays (k_i, 3) rad/s; ``intervals``:
    the time each sample stands for (``centred_intervals`` or ``hold_intervals``).
    Padded samples have ``dt = 0`` and so rotate by nothing.
    """
    return _padded(rate, [intervals(ti) for ti in t])


def _padded(rate: Sequence[np.ndarray], dts: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``pad_turns`` of turns whose intervals ``dts`` are already formed."""
    m = len(rate)
    k_max = max((len(w) for w in rate), default=0)
    w_pad = np.zeros((m, max(k_max, 1), 3))
    dt_pad = np.zeros((m, max(k_max, 1)))
    for i, (wi, di) in enumerate(zip(rate, dts, strict=True)):
        w_pad[i, : len(wi)] = wi
        dt_pad[i, : len(wi)] = di
    return w_pad, dt_pad


TURN_CHUNK = 64  # turns integrated at once: a long recording's corrected rates are never all formed


def _lengths(dt: np.ndarray) -> np.ndarray:
    """(m,) each padded turn's samples through its last nonzero interval (1 for none)."""
    if not dt.shape[1]:
        return np.ones(len(dt), np.int64)
    return np.where(dt.any(axis=1), dt.shape[1] - np.argmax(dt[:, ::-1] != 0, axis=1), 1)


def _length_groups(length: np.ndarray) -> list[np.ndarray]:
    """The indices of turns within a factor two in ``length``, group by group."""
    group = np.ceil(np.log2(length)).astype(int)
    return [np.flatnonzero(group == g) for g in np.unique(group)]


def _turn_products(rate: np.ndarray, dt: np.ndarray, M: np.ndarray | None = None,
                   turns: np.ndarray | None = None) -> np.ndarray:
    """(m, 4) ``compose(quat_exp((rate @ M.T) * dt))`` of padded turns (``turns``: those alone,
    in that order), by groups of turns within a factor two in length: each group stops at its
    longest turn, so a few long turns (a turntable's) do not make every short one integrate
    their padding. Padding is an exact identity factor, so the products are those of the whole
    padded arrays. ``TURN_CHUNK`` turns at a time: no copy of the (selected, corrected) rates."""
    turns = np.arange(len(dt)) if turns is None else np.asarray(turns, dtype=np.int64)
    length = np.ones(len(turns), np.int64)
    for a in range(0, len(turns), TURN_CHUNK):
        length[a:a + TURN_CHUNK] = _lengths(dt[turns[a:a + TURN_CHUNK]])
    out = np.empty((len(turns), 4))
    for pos in _length_groups(length):
        n = int(length[pos].max())
        for a in range(0, len(pos), TURN_CHUNK):
            p = pos[a:a + TURN_CHUNK]
            w = rate[turns[p], :n] if M is None else rate[turns[p], :n] @ M.T
            out[p] = _compose_first(_quat_exp_first(w * dt[turns[p], :n, None])).T
    return out


def turn_quaternions(rate: np.ndarray, dt: np.ndarray, M: np.ndarray | None = None,
                     turns: np.ndarray | None = None) -> np.ndarray:
    """Unit quaternions (m, 4) of padded turns: ``rate`` (m, k, 3) rad/s, ``dt`` (m, k) s.

    ``rate`` is already corrected (bias removed), then by ``M`` when given (``rate @ M.T``);
    ``turns``: those turns alone.
    """
    q = _turn_products(rate, dt, M, turns)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def turn_rotations(rate: np.ndarray, dt: np.ndarray, M: np.ndarray | None = None,
                   turns: np.ndarray | None = None) -> np.ndarray:
    """Rotation matrices (m, 3, 3) of padded turns, as ``turn_quaternions``."""
    return quat_to_matrix(_turn_products(rate, dt, M, turns))  # normalises once


def _ragged_products(t: Sequence[np.ndarray], rate: Sequence[np.ndarray],
                     intervals: Callable[[np.ndarray], np.ndarray], bias: np.ndarray | None,
                     M: np.ndarray | None) -> np.ndarray:
    """``_turn_products`` of ``pad_turns(t, rate, intervals)`` less ``bias`` (m, 3) per turn,
    without padding every turn to the longest (at 1 h, 23 MiB for 5 MiB of samples, where a
    turntable turn lasts 20 s): each of its groups (turns within a factor two in length) is
    padded alone, and its products are formed from the same rows: the same numbers."""
    m = len(t)
    out = np.empty((m, 4))
    dts = [intervals(ti) for ti in t]  # once: they give the lengths and are the padded intervals
    length = np.array([_lengths(d[None])[0] for d in dts], np.int64)
    for idx in _length_groups(length):
        r, dt = _padded([rate[i] for i in idx], [dts[i] for i in idx])
        if bias is not None:
            r -= np.broadcast_to(bias, (m, 3))[idx][:, None, :]
        out[idx] = _turn_products(r, dt, M)
    return out


def ragged_turn_quaternions(t: Sequence[np.ndarray], rate: Sequence[np.ndarray],
                            intervals: Callable[[np.ndarray], np.ndarray] = centred_intervals,
                            bias: np.ndarray | None = None, M: np.ndarray | None = None) -> np.ndarray:
    """``turn_quaternions`` of ``pad_turns(t, rate, intervals)`` with each turn's ``bias``
    (m, 3) subtracted, the turns padded by groups of similar length, not all to the longest."""
    q = _ragged_products(t, rate, intervals, bias, M)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def ragged_turn_rotations(t: Sequence[np.ndarray], rate: Sequence[np.ndarray],
                          intervals: Callable[[np.ndarray], np.ndarray] = centred_intervals,
                          bias: np.ndarray | None = None, M: np.ndarray | None = None) -> np.ndarray:
    """``turn_rotations`` likewise (``ragged_turn_quaternions``)."""
    return quat_to_matrix(_ragged_products(t, rate, intervals, bias, M))


def carry(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """World-fixed vectors ``v`` (m, 3) seen in the body after it turned by ``R`` (m, 3, 3):
    ``R^T v``, Eq. (2.16)."""
    return np.einsum("mji,mj->mi", R, v)

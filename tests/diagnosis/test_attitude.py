"""Motion attitudes from the calibrated gyro: exact integration, segmented scans, sensitivities."""

from __future__ import annotations

import numpy as np

from imupipe.diagnosis.attitude import (
    Attitude,
    MotionSamples,
    Quadrature,
    by_motion,
    left_jacobian,
    segmented_cumsum,
    segmented_scan,
    weighted,
)
from imupipe.rotations import (
    compose,
    exp_so3,
    quat_exp,
    quat_mul,
    quat_mul_into,
    quat_to_matrix,
    skew,
)


def _motions(rng, m=4):
    t, y = [], []
    t0 = 0.0
    for j in range(m):
        k = int(rng.integers(3, 40))
        tj = t0 + np.cumsum(rng.uniform(0.008, 0.012, k))
        t.append(tj)
        y.append(rng.normal(size=(k, 3)))
        t0 = tj[-1] + 5.0
    return t, y


def test_segmented_scan_and_cumsum_restart_per_segment():
    rng = np.random.default_rng(0)
    seg = np.repeat([0, 1, 2], [5, 1, 7])
    q = quat_exp(rng.normal(size=(13, 3)) * 0.3)
    out = segmented_scan(q, seg)
    for s in range(3):
        idx = np.flatnonzero(seg == s)
        for k in range(len(idx)):
            want = compose(q[idx[: k + 1]][None])[0]
            assert np.allclose(quat_to_matrix(out[idx[k]]), quat_to_matrix(want), atol=1e-12)
    x = rng.normal(size=(13, 2))
    c = segmented_cumsum(x, seg)
    assert np.allclose(c[5:6], x[5:6]) and np.allclose(c[:5], np.cumsum(x[:5], 0))


def test_quaternion_product_on_components_is_the_same_bits():
    """The product on component rows, into a buffer, and quat_mul on (..., 4) arrays, against
    the Hamilton product written out: bit for bit."""
    rng = np.random.default_rng(3)
    p, q = rng.normal(size=(2, 1000, 4))
    (pw, px, py, pz), (qw, qx, qy, qz) = p.T, q.T
    want = np.stack([pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw], axis=-1)
    out = quat_mul_into(np.ascontiguousarray(p.T), np.ascontiguousarray(q.T), np.empty((4, 1000)), np.empty(1000))
    assert np.array_equal(out.T, want)
    assert np.array_equal(quat_mul(p.reshape(10, 100, 4), q.reshape(10, 100, 4)), want.reshape(10, 100, 4))
    assert np.array_equal(quat_mul(p[:1], q), quat_mul(np.repeat(p[:1], 1000, 0), q))  # broadcast


def test_rotation_matrices_and_cross_products_of_any_leading_shape():
    """quat_to_matrix and skew, written entry by entry: the rotation of exp_so3 and the cross
    product, for stacks of any shape."""
    rng = np.random.default_rng(8)
    v, u = rng.normal(size=(2, 5, 7, 3))
    np.testing.assert_allclose(skew(v) @ u[..., None], np.cross(v, u)[..., None], rtol=1e-14, atol=1e-14)
    angle = np.linalg.norm(v, axis=-1)
    R = quat_to_matrix(quat_exp(v))
    want = np.stack([[exp_so3(v[i, j] / angle[i, j], angle[i, j]) for j in range(7)] for i in range(5)])
    np.testing.assert_allclose(R, want, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    assert quat_to_matrix(np.array([2.0, 0, 0, 0])).tolist() == np.eye(3).tolist()  # normalised first


def test_smooth_rotation_about_a_fixed_axis_is_integrated_to_fourth_order():
    """Minimum-jerk turn of 2 rad in 2 s sampled at 100 Hz with jittered stamps: the attitude at
    any instant (between samples too) within 1e-9 rad of the exact one."""
    rng = np.random.default_rng(1)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    T, A = 2.0, 2.0

    def angle(t):
        s = np.clip(t / T, 0, 1)
        return A * (10 * s**3 - 15 * s**4 + 6 * s**5)

    def rate(t):
        s = np.clip(t / T, 0, 1)
        return A / T * (30 * s**2 - 60 * s**3 + 30 * s**4)

    t = np.sort(np.r_[0.0, np.arange(1, 200) * 0.01 + rng.uniform(-2e-3, 2e-3, 199), T])
    ms = MotionSamples.from_turns([t], [np.outer(rate(t), axis)])
    att = Attitude.integrate(Quadrature(ms), ms.y)
    tt = np.linspace(0.0, T, 331)
    R = att.rotation_at(att.quad.points(tt, np.zeros(len(tt), int)))
    want = np.stack([exp_so3(axis, angle(x)) for x in tt])
    assert np.abs(R - want).max() < 1e-9
    assert np.abs(att.total[0] - exp_so3(axis, A)).max() < 1e-9


def test_constant_rate_is_exact():
    rng = np.random.default_rng(1)
    t, y = _motions(rng)
    ms = MotionSamples.from_turns(t, y)
    # constant rate: the rotation at any instant is exp(w (t - origin))
    w = np.array([0.3, -0.2, 0.5])
    att = Attitude.integrate(Quadrature(ms), np.tile(w, (len(ms), 1)))
    j = 2
    tt = np.linspace(ms.origin[j], ms.end[j], 17)
    R = att.rotation_at(att.quad.points(tt, np.full(len(tt), j)))
    want = np.stack([exp_so3(w / np.linalg.norm(w), np.linalg.norm(w) * (x - ms.origin[j])) for x in tt])
    assert np.allclose(R, want, atol=1e-12)


def test_attitude_sensitivity_matches_finite_differences():
    rng = np.random.default_rng(2)
    t, y = _motions(rng, 3)
    ms = MotionSamples.from_turns(t, y)
    M = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    b = 0.1 * rng.normal(size=3)

    def omega(theta):
        return (ms.y - theta[9:]) @ theta[:9].reshape(3, 3).T

    theta = np.r_[M.ravel(), b]
    # d omega / d theta per sample: (N, 3, 12)
    D = np.zeros((len(ms), 3, 12))
    e = ms.y - b
    for i in range(3):
        D[:, i, 3 * i:3 * i + 3] = e
    D[:, :, 9:] = -M
    quad = Quadrature(ms)
    att = Attitude.integrate(quad, omega(theta))
    motion = ms.motion[::3]
    tt = ms.t[::3] + 0.003
    pts = quad.points(tt, motion)
    S = att.sensitivity(D, pts)
    R0 = att.rotation_at(pts)
    for p in (0, 4, 8, 9, 11):
        d = np.zeros(12)
        d[p] = 1e-6
        Rp = Attitude.integrate(quad, omega(theta + d)).rotation_at(pts)
        Rm = Attitude.integrate(quad, omega(theta - d)).rotation_at(pts)
        dR = (Rp - Rm) / 2e-6 @ np.swapaxes(R0, 1, 2)  # [phi]x in the start frame
        phi = np.stack([dR[:, 2, 1], dR[:, 0, 2], dR[:, 1, 0]], -1)
        assert np.allclose(phi, S[:, :, p], atol=1e-7), p
    end = att.end_sensitivity(D)
    last = np.flatnonzero(np.r_[ms.motion[1:] != ms.motion[:-1], True])
    at_last = att.sensitivity(D, quad.points(ms.t[last], ms.motion[last]))
    assert np.allclose(end, at_last, atol=1e-12)


def test_left_jacobian_small_and_large_angles():
    a = np.array([[1e-6, 0, 0], [0.3, -0.4, 1.2]])
    J = left_jacobian(a)
    for k in range(2):
        eps = 1e-7
        for i in range(3):
            d = np.zeros(3)
            d[i] = eps
            R = quat_to_matrix(quat_exp(a[k]))
            dR = (quat_to_matrix(quat_exp(a[k] + d)) - quat_to_matrix(quat_exp(a[k] - d))) / (2 * eps) @ R.T
            col = np.array([dR[2, 1], dR[0, 2], dR[1, 0]])
            assert np.allclose(col, J[k][:, i], atol=1e-7)


def test_by_motion_slices_are_the_masks_of_sorted_labels():
    motion = np.array([0, 0, 2, 2, 2, 3, 5])  # motions 1 and 4 without samples
    slices = by_motion(motion, 6)
    assert len(slices) == 6
    for j, sel in enumerate(slices):
        assert np.array_equal(np.arange(len(motion))[sel], np.flatnonzero(motion == j))
    assert [s.stop - s.start for s in by_motion(np.zeros(0, int), 2)] == [0, 0]


def test_attitude_formed_by_ranges_of_steps_equals_it_formed_at_once(monkeypatch):
    from imupipe.diagnosis import attitude

    rng = np.random.default_rng(3)
    ms = MotionSamples.from_turns(*_motions(rng, m=6))
    D = rng.normal(size=(len(ms), 3, 5))
    got = []
    for size in (1 << 20, 20):  # at once; by 20 rows, or ranges of whole motions about 20 steps long
        monkeypatch.setattr(attitude, "STEP_CHUNK", size)
        quad = Quadrature(ms)
        att = Attitude.integrate(quad, ms.y * 0.5)
        pts = quad.points(ms.t[::2] + 0.002, ms.motion[::2])
        got.append((quad.A.toarray(), pts.W.toarray(), att.rotations_before(slice(None)), att.total, att.rotation_at(pts),
                    att.end_sensitivity(D), att.sensitivity(D, pts)))
        starts = np.flatnonzero(np.r_[True, quad.seg[1:] != quad.seg[:-1]])
        assert [a for a, _ in quad.ranges] == sorted({a for a, _ in quad.ranges} & set(starts))
        assert quad.ranges[-1][1] == len(quad.step)
    assert len(quad.ranges) > 2
    for whole, ranged in zip(*got, strict=True):
        assert np.allclose(whole, ranged, rtol=1e-13, atol=1e-13)


def test_the_same_rates_again_give_the_attitude_integrated_last():
    """A fit asks again for the point it has just evaluated: rates equal to the last ones (another
    array) give that attitude back; other rates are integrated afresh, to the bits of a fresh
    quadrature's integration."""
    rng = np.random.default_rng(5)
    ms = MotionSamples.from_turns(*_motions(rng, m=5))
    quad = Quadrature(ms)
    first = Attitude.integrate(quad, ms.y * 0.5)
    again = Attitude.integrate(quad, (ms.y * 0.5).copy())
    assert all(getattr(again, n) is getattr(first, n) for n in ("omega", "q_before", "total"))
    other = ms.y * 0.5
    other[3, 1] += 1e-12
    moved = Attitude.integrate(quad, other)
    fresh = Attitude.integrate(Quadrature(ms), other)
    assert moved.q_before is not first.q_before
    for name in ("q_before", "total"):
        assert np.array_equal(getattr(moved, name), getattr(fresh, name))
    assert Attitude.integrate(quad, ms.y * 0.5).q_before is not first.q_before  # one attitude is kept, the last


def test_the_attitude_kept_is_let_go_before_other_rates_are_integrated(monkeypatch):
    """Only the attitude being formed and none kept: the last one's arrays are released first
    (at a fit's peak they were two attitudes, 8.4 MiB at 1 h)."""
    import weakref

    from imupipe.diagnosis import attitude

    rng = np.random.default_rng(6)
    ms = MotionSamples.from_turns(*_motions(rng, m=3))
    quad = Quadrature(ms)
    Attitude.integrate(quad, ms.y * 0.5)
    kept = weakref.ref(quad.last_integrated[1])  # its q_before
    seen = []
    scan = attitude.segmented_scan
    monkeypatch.setattr(attitude, "segmented_scan", lambda q, seg: (seen.append(kept()), scan(q, seg))[1])
    Attitude.integrate(quad, ms.y * 0.25)
    assert seen and all(x is None for x in seen)


def test_rotations_before_some_steps_are_the_bits_of_all_steps_rotations():
    """The attitude keeps quaternions and forms the matrices where used: those of a few steps,
    picked or sliced, are the very numbers of all steps' matrices formed at once."""
    rng = np.random.default_rng(4)
    ms = MotionSamples.from_turns(*_motions(rng, m=5))
    att = Attitude.integrate(Quadrature(ms), ms.y * 0.5)
    every = att.rotations_before(slice(None))
    picked = rng.integers(0, len(att.q_before), 40)
    assert np.array_equal(att.rotations_before(picked), every[picked])
    assert np.array_equal(att.rotations_before(slice(7, 29)), every[7:29])
    starts = np.r_[0, np.flatnonzero(np.diff(att.quad.seg)) + 1]  # each motion's first step: no rotation yet
    assert np.array_equal(every[starts], np.broadcast_to(np.eye(3), (len(starts), 3, 3)))


def test_sensitivity_forms_the_sums_before_steps_over_its_instants_motions_alone():
    """``sensitivity`` forms the running sums before each step over the whole motions holding its
    instants (no (S, 3, P) array through a fit): the bits of the running sums over every step at
    once, for chunks of instants that start or end inside a motion, and instants of a motion
    without steps; the end totals (each motion's sum) are the running sums' last ones."""
    rng = np.random.default_rng(5)
    t, y = _motions(rng, m=6)
    t[3], y[3] = t[3][:1], y[3][:1]  # a motion of one sample: no step
    ms = MotionSamples.from_turns(t, y)
    D = rng.normal(size=(len(ms), 3, 4))
    quad = Quadrature(ms)
    pts = quad.points(ms.t + 0.002, ms.motion)
    att = Attitude.integrate(quad, ms.y * 0.5)
    per, run = att._per_step(D, 0, len(att.q_before))  # every step's, and their running sums, at once
    ends = att.end_sensitivity(D)
    np.testing.assert_array_equal(ends[quad.seg[quad.last]], run[quad.last])
    hh = np.maximum(pts.h, 0)
    within = att.rotations_before(hh) @ left_jacobian(pts.W @ att.omega) @ weighted(pts.W, D)
    want = np.where((pts.h >= 0)[:, None, None], (run - per)[hh] + within, 0.0)
    for a, b in ((0, len(ms)), (5, 17), (20, 21), (30, 80)):
        np.testing.assert_array_equal(att.sensitivity(D, pts.subset(slice(a, b))), want[a:b])


def test_steady_sampling_shares_its_node_patterns_with_the_same_weights(monkeypatch):
    """Samples at a steady rate give a few node patterns, each inverted once; jittered ones are
    inverted row by row. Both give the quadrature weights of the row-by-row path, bit for bit."""
    from imupipe.diagnosis import attitude

    rng = np.random.default_rng(4)
    steady = [5.0 * j + np.arange(int(rng.integers(3, 300))) * 0.01 for j in range(8)]
    jittered = [t + rng.uniform(0, 1e-4, len(t)) for t in steady]
    for turns in (steady, jittered):
        ms = MotionSamples.from_turns(turns, [np.zeros((len(t), 3)) for t in turns])
        at = (ms.t[:-1] + 0.003, ms.motion[:-1])
        shared, points = Quadrature(ms).A, Quadrature(ms).points(*at).W
        monkeypatch.setattr(attitude, "_PATTERN_PROBE", len(ms))  # no probe passes: row by row
        for a, b in ((shared, Quadrature(ms).A), (points, Quadrature(ms).points(*at).W)):
            assert (a != b).nnz == 0 and np.array_equal(a.indices, b.indices)
        monkeypatch.undo()
    inverted = []
    inv = np.linalg.inv
    monkeypatch.setattr(np.linalg, "inv", lambda V: inverted.append(len(V)) or inv(V))
    for turns in (steady, jittered):
        Quadrature(MotionSamples.from_turns(turns, [np.zeros((len(t), 3)) for t in turns]))
    steps = sum(len(t) for t in steady) - len(steady)
    assert 5 * inverted[0] < steps and inverted[1] == steps  # steady: far fewer patterns; jittered: each step

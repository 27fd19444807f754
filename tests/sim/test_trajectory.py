"""Motion is exact: static specific force, attitude from the integrated rate, lever-arm kinematics."""

from __future__ import annotations

import numpy as np

from imupipe.rotations import angle_between, exp_so3, random_rotation
from imupipe.sim.environment import Environment
from imupipe.sim.trajectory import Rest, Rotate, Trajectory, Translate

G = Environment().g


def _trajectory(seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    segs = []
    for _ in range(6):
        segs.append(Rest(1.0))
        segs.append(Rotate(tuple(rng.normal(size=3)), rng.uniform(-2.5, 2.5), rng.uniform(0.5, 2.0)))
    segs += [Rest(0.5), Translate((1.0, -2.0, 0.5), 2.0), Rest(0.5)]
    return Trajectory(tuple(segs), random_rotation(rng))


def test_static_specific_force_has_norm_g():
    traj = _trajectory()
    rests = [(a, b) for a, b, s in traj.boundaries() if isinstance(s, Rest)]
    t = np.concatenate([np.linspace(a, b, 50, endpoint=False) for a, b in rests])
    f = traj.evaluate(t).specific_force(G)
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), G, rtol=0, atol=1e-12)


def test_integrated_rate_reproduces_attitude():
    """Integrate the body rate segment by segment (midpoint rule, fixed axis per segment) and
    compose: the result is the trajectory's attitude at every segment end."""
    traj = _trajectory(1)
    R = traj.attitude_at_segment_start(0)
    for i, (a, b, _seg) in enumerate(traj.boundaries()):
        n = 4000
        tm = a + (np.arange(n) + 0.5) * (b - a) / n
        for w in traj.evaluate(tm).omega:
            angle = np.linalg.norm(w) * (b - a) / n
            if angle > 0:
                R = R @ exp_so3(w / np.linalg.norm(w), angle)
        assert float(angle_between(R, traj.attitude_at_segment_start(i + 1))) < 1e-9


def test_lever_arm_term_is_alpha_cross_r_plus_centripetal():
    traj = _trajectory(2)
    r = np.array([0.03, -0.02, 0.05])
    t = np.linspace(0.2, traj.duration_s - 0.2, 400)
    kin = traj.evaluate(t)
    expected = np.cross(kin.alpha, r) + np.cross(kin.omega, np.cross(kin.omega, r))
    np.testing.assert_allclose(kin.specific_force(G, r) - kin.specific_force(G), expected, atol=1e-12)
    # and independently: the second derivative of the point's world position, by finite differences
    h = 1e-4
    pos = [traj.evaluate(t + d) for d in (-h, 0.0, h)]
    point = [k.p + np.einsum("nij,j->ni", k.R, r) for k in pos]
    acc_world = (point[0] - 2 * point[1] + point[2]) / h**2
    f_fd = np.einsum("nji,nj->ni", kin.R, acc_world + [0.0, 0.0, G])
    np.testing.assert_allclose(f_fd, kin.specific_force(G, r), atol=2e-6)


def test_rate_is_derivative_of_attitude():
    traj = _trajectory(3)
    t = np.linspace(0.1, traj.duration_s - 0.1, 200)
    h = 1e-6
    Rp, Rm = traj.evaluate(t + h).R, traj.evaluate(t - h).R
    W = np.einsum("nji,njk->nik", traj.evaluate(t).R, (Rp - Rm) / (2 * h))
    w_fd = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], 1)
    np.testing.assert_allclose(w_fd, traj.evaluate(t).omega, atol=1e-7)


def test_segments_compose_exactly():
    traj = _trajectory(4)
    for i, (a, _b, _s) in enumerate(traj.boundaries()):
        np.testing.assert_allclose(traj.evaluate(np.array([a])).R[0], traj.attitude_at_segment_start(i), atol=1e-12)

"""Motion evaluated analytically at any time: rests, rotations, translations.

World frame: ENU (x east, y north, z up). ``R`` is body-to-world
(``v_world = R @ v_body``); the body frame is the instrument frame. A
trajectory is a list of segments composed exactly: each segment starts from
the end state of the one before. Rotations are about a body-fixed axis with a
minimum-jerk angle profile (rate and angular acceleration zero at both ends),
so attitude, body rate and angular acceleration are closed-form everywhere and
time offsets and lever arms are exact. Translations carry the unit to another
place (the ``place`` index counts them) without turning it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..rotations import exp_so3


def min_jerk(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimum-jerk profile h(s) and its first two derivatives in s, for s in [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    h = s**3 * (10 - 15 * s + 6 * s**2)
    dh = 30 * s**2 * (1 - s) ** 2
    ddh = 60 * s * (1 - s) * (1 - 2 * s)
    return h, dh, ddh


@dataclass(frozen=True)
class Rest:
    """The unit held still for ``duration_s`` seconds."""

    duration_s: float
    label: str = "rest"


@dataclass(frozen=True)
class Rotate:
    """Turn by ``angle_rad`` about the unit body-frame ``axis`` in ``duration_s`` seconds."""

    axis: tuple[float, float, float]
    angle_rad: float
    duration_s: float
    label: str = "turn"

    def unit_axis(self) -> np.ndarray:
        a = np.asarray(self.axis, dtype=float)
        return a / np.linalg.norm(a)


@dataclass(frozen=True)
class Translate:
    """Carry the unit by ``displacement_m`` (world ENU, m) in ``duration_s`` without turning it."""

    displacement_m: tuple[float, float, float]
    duration_s: float
    label: str = "move"


Segment = Rest | Rotate | Translate


@dataclass(frozen=True)
class Kinematics:
    """The motion at times ``t`` (n,), s.

    ``R`` (n, 3, 3) body-to-world; ``omega``, ``alpha`` (n, 3) body rate (rad/s) and
    angular acceleration (rad/s^2) in body axes; ``p`` (n, 3) position (m, world);
    ``a`` (n, 3) linear acceleration of the centre of rotation (m/s^2, world);
    ``place`` (n,) place index, fractional while being carried.
    """

    t: np.ndarray
    R: np.ndarray
    omega: np.ndarray
    alpha: np.ndarray
    p: np.ndarray
    a: np.ndarray
    place: np.ndarray

    def specific_force(self, gravity_m_s2: float, r_body: np.ndarray | None = None) -> np.ndarray:
        """Specific force (n, 3), m/s^2, body axes, at body point ``r_body`` (m) off the centre.

        World ENU: gravity is (0, 0, -g), so f = R^T (a + (0, 0, g)) + alpha x r + omega x (omega x r).
        """
        f = np.einsum("nji,nj->ni", self.R, self.a + np.array([0.0, 0.0, gravity_m_s2]))
        if r_body is not None:
            r = np.asarray(r_body, dtype=float)
            f = f + np.cross(self.alpha, r) + np.cross(self.omega, np.cross(self.omega, r))
        return f

    def to_body(self, v_world: np.ndarray) -> np.ndarray:
        """A world vector (3,) or (n, 3) in body axes, (n, 3)."""
        v = np.broadcast_to(np.asarray(v_world, dtype=float), (len(self.t), 3))
        return np.einsum("nji,nj->ni", self.R, v)


@dataclass(frozen=True)
class Trajectory:
    """Segments composed from the initial attitude ``R0`` (body-to-world) and position ``p0``."""

    segments: tuple[Segment, ...]
    R0: np.ndarray = field(default_factory=lambda: np.eye(3))
    p0: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        starts, Rs, ps, places = [0.0], [np.asarray(self.R0, float)], [np.asarray(self.p0, float)], [0]
        for seg in self.segments:
            R, p, place = Rs[-1], ps[-1], places[-1]
            if isinstance(seg, Rotate):
                R = R @ exp_so3(seg.unit_axis(), seg.angle_rad)
            elif isinstance(seg, Translate):
                p = p + np.asarray(seg.displacement_m, float)
                place += 1
            starts.append(starts[-1] + seg.duration_s)
            Rs.append(R)
            ps.append(p)
            places.append(place)
        object.__setattr__(self, "_starts", np.array(starts))
        object.__setattr__(self, "_R", np.array(Rs))
        object.__setattr__(self, "_p", np.array(ps))
        object.__setattr__(self, "_places", np.array(places, dtype=float))

    @property
    def duration_s(self) -> float:
        return float(self._starts[-1])

    def boundaries(self) -> list[tuple[float, float, Segment]]:
        """(t_start_s, t_end_s, segment) for every segment."""
        return [(float(self._starts[i]), float(self._starts[i + 1]), s) for i, s in enumerate(self.segments)]

    def attitude_at_segment_start(self, i: int) -> np.ndarray:
        """Body-to-world attitude (3, 3) at the start of segment ``i`` (``i = len`` gives the end)."""
        return self._R[i].copy()

    def evaluate(self, t: np.ndarray) -> Kinematics:
        """The exact motion at times ``t`` (n,) s; before 0 and after the end the unit is still."""
        t = np.asarray(t, dtype=float)
        n = len(t)
        R = np.empty((n, 3, 3))
        omega, alpha, p, a = (np.zeros((n, 3)) for _ in range(4))
        place = np.empty(n)
        idx = np.clip(np.searchsorted(self._starts, t, side="right") - 1, 0, len(self.segments))
        for i in np.unique(idx):
            m = idx == i
            R[m], p[m], place[m] = self._R[i], self._p[i], self._places[i]
            if i >= len(self.segments):
                continue
            seg, T = self.segments[i], self.segments[i].duration_s
            s = (t[m] - self._starts[i]) / T
            h, dh, ddh = min_jerk(s)
            if isinstance(seg, Rotate):
                ax = seg.unit_axis()
                R[m] = self._R[i] @ exp_so3(ax, seg.angle_rad * h)
                omega[m] = np.outer(seg.angle_rad * dh / T, ax)
                alpha[m] = np.outer(seg.angle_rad * ddh / T**2, ax)
            elif isinstance(seg, Translate):
                d = np.asarray(seg.displacement_m, float)
                p[m] = self._p[i] + np.outer(h, d)
                a[m] = np.outer(ddh / T**2, d)
                place[m] = self._places[i] + h
        return Kinematics(t, R, omega, alpha, p, a, place)

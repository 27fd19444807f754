"""Calibration sessions as motion plans, selectable by name, parameters with the papers' defaults.

A protocol builds a ``Plan``: the trajectory (``imupipe.sim.trajectory``), the
powered windows (the unit records only while powered; a gap is a power cycle)
and the labels of its segments (``warmup``, ``rest``, ``reference_y_up``,
``reference_x_up``, ``roll_turn``, ``turn``, ``reposition``, ...). World ENU:
"instrument Y up" means the body y axis along world z.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationError

from ..components import Params
from ..errors import ConfigError, describe_validation
from ..rotations import align, matrix_to_rotvec, random_rotation
from .trajectory import Rest, Rotate, Segment, Trajectory, Translate

UP = np.array([0.0, 0.0, 1.0])
EX, EY, EZ = np.eye(3)
DEG = np.pi / 180.0


@dataclass(frozen=True)
class Plan:
    """A session: ``trajectory``, powered ``windows`` [(t_on_s, t_off_s), ...], ``thermal`` overrides."""

    trajectory: Trajectory
    windows: tuple[tuple[float, float], ...]
    thermal: dict[str, Any]


class Builder:
    """Appends segments while tracking the attitude, so later moves can aim at world directions."""

    def __init__(self, R0: np.ndarray):
        self.R0 = np.asarray(R0, float)
        self.R = self.R0.copy()
        self.segments: list[Segment] = []

    def rest(self, duration_s: float, label: str = "rest") -> None:
        self.segments.append(Rest(duration_s, label))

    def rotate(self, axis_body: np.ndarray, angle_rad: float, duration_s: float, label: str = "turn") -> None:
        seg = Rotate(tuple(np.asarray(axis_body, float) / np.linalg.norm(axis_body)), float(angle_rad),
                     duration_s, label)
        self.segments.append(seg)
        self.R = Trajectory((seg,), self.R).attitude_at_segment_start(1)

    def rotate_world(self, axis_world: np.ndarray, angle_rad: float, duration_s: float, label: str = "turn") -> None:
        """Turn about a world-fixed axis (a gimbal or turntable axis)."""
        self.rotate(self.R.T @ np.asarray(axis_world, float), angle_rad, duration_s, label)

    def goto(self, R_target: np.ndarray, rate_rad_s: float = 45 * DEG, label: str = "reposition") -> None:
        """Turn by the shortest rotation to attitude ``R_target`` (body-to-world)."""
        rv = matrix_to_rotvec(self.R.T @ R_target)
        angle = np.linalg.norm(rv)
        if angle < 1e-9:
            return
        self.rotate(rv / angle, angle, max(3.0, 1.875 * angle / rate_rad_s), label)

    def translate(self, displacement_m: np.ndarray, duration_s: float, label: str = "move") -> None:
        self.segments.append(Translate(tuple(np.asarray(displacement_m, float)), duration_s, label))

    def build(self) -> Trajectory:
        return Trajectory(tuple(self.segments), self.R0)


def up_in_body(R: np.ndarray) -> np.ndarray:
    return R.T @ UP


def attitude_with_up(body_axis: np.ndarray, heading_rad: float = 0.0) -> np.ndarray:
    """Body-to-world attitude with ``body_axis`` pointing up, turned by ``heading_rad`` about the vertical."""
    return align(body_axis, UP, heading_rad)


# --------------------------------------------------------------------------- pieces


def references(b: Builder, rng: np.random.Generator, rest_s: float, roll_turn_deg: float) -> None:
    """The sphere-rig paper's reference positions: Y up (eq. 17-18), the roll turn that scales the
    gyro (eq. 37, Y up to Z down), X up (eq. 19)."""
    b.goto(attitude_with_up(EY, rng.uniform(0, 2 * np.pi)))
    b.rest(rest_s, "reference_y_up")
    b.rotate(EX, roll_turn_deg * DEG, 8.0, "roll_turn")
    b.rest(rest_s, "reference_z_down" if abs(roll_turn_deg - 90) < 1e-9 else "after_roll_turn")
    b.goto(attitude_with_up(EX, rng.uniform(0, 2 * np.pi)))
    b.rest(rest_s, "reference_x_up")


def small_turn_path(b: Builder, rng: np.random.Generator, n: int, rest_s: float, turn_s: float,
                    max_turn_deg: float, path: str, passes: int, reposition_every: int) -> None:
    """``n`` rests joined by turns of at most ``max_turn_deg``.

    ``steered``: the up direction (in body axes) is led along ``passes`` pole-to-pole spirals,
    phase-shifted and alternating in sense, with a random twist about the vertical;
    ``walk``: an operator's unsteered random walk, with a large repositioning every
    ``reposition_every`` rests (0: never).
    """
    max_turn = max_turn_deg * DEG
    targets = _spiral_targets(n, passes, max_turn * 0.8) if path == "steered" else None
    for i in range(n):
        b.rest(rest_s, "rest")
        if i == n - 1:
            break
        if path == "walk" and reposition_every and (i + 1) % reposition_every == 0:
            b.goto(random_rotation(rng), 30 * DEG)
            continue
        if targets is not None:
            u = up_in_body(b.R)
            target = targets[i + 1]
            n_ax = np.cross(u, target)
            ang = np.arctan2(np.linalg.norm(n_ax), u @ target)
            tilt = -n_ax / np.linalg.norm(n_ax) * min(ang, 0.8 * max_turn) if ang > 1e-9 else np.zeros(3)
            rv = tilt + u * rng.uniform(-0.5, 0.5) * max_turn
        else:
            rv = rng.normal(size=3)
            rv *= rng.uniform(0.2, 1.0) * max_turn / np.linalg.norm(rv)
        angle = np.linalg.norm(rv)
        if angle > max_turn:
            rv, angle = rv * max_turn / angle, max_turn
        if angle < 1e-6:
            rv, angle = u * 0.5 * max_turn, 0.5 * max_turn
        b.rotate(rv / angle, angle, turn_s, "turn")


def _spiral_targets(n: int, passes: int, step: float) -> np.ndarray:
    """Up directions (n, 3) along ``passes`` phase-shifted pole-to-pole spirals, alternating sense."""
    per = int(np.ceil(n / passes))
    out = []
    for j in range(passes):
        s = np.linspace(0, 1, per)
        theta = np.pi * s if j % 2 == 0 else np.pi * (1 - s)
        length = per * step  # path length available; spend what the meridian does not need on windings
        wind = np.sqrt(max(length**2 - np.pi**2, 0.0)) / (2 * np.pi * 0.64)
        phi = 2 * np.pi * (wind * s + j / passes)
        out.append(np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1))
    return np.concatenate(out)[:n]


def turntable(b: Builder, mountings: list[np.ndarray], turn_s: float, rest_s: float, rng) -> None:
    """Full turns about the vertical (one each sense) in each mounting (body axis up)."""
    for axis in mountings:
        b.goto(attitude_with_up(axis, rng.uniform(0, 2 * np.pi)))
        b.rest(rest_s, "turntable_rest")
        for sense in (1, -1):
            b.rotate_world(UP, sense * 2 * np.pi, turn_s, "turntable_turn")
            b.rest(rest_s, "turntable_rest")


# --------------------------------------------------------------------------- protocols


class SphereRigParams(Params):
    """Method A's sphere rig: warm-up, random positions (accel/mag), small turns (gyro), references."""

    warmup_s: float = Field(600.0, ge=0, description="rest after power-on (the paper: 3600)")
    n_positions: int = Field(200, ge=10, description="static positions uniform over the sphere (paper: >= 200)")
    n_turns: int = Field(100, ge=0, description="rests joined by small turns for the gyro (paper: 288)")
    rest_s: float = Field(5.0, gt=0)
    turn_s: float = Field(5.0, gt=0)
    max_turn_deg: float = Field(5.0, gt=0, le=30)
    path: Literal["steered", "walk"] = "steered"
    passes: int = Field(4, ge=1)
    reposition_every: int = Field(40, ge=0)
    reference_rest_s: float = Field(10.0, gt=0)
    roll_turn_deg: float = Field(90.0, gt=0, le=90)


class OneStageParams(SphereRigParams):
    """Method A, one stage: one recording of rests joined by small turns covering the sphere."""

    n_positions: int = Field(300, ge=10)
    n_turns: int = 0


class GimbalParams(Params):
    """Method B's three-axis gimbal: 20-deg grid over two axes, then random 2-s rotations."""

    grid_deg: float = Field(20.0, gt=0)
    rest_s: float = Field(5.0, gt=0)
    step_s: float = Field(1.5, gt=0)
    n_rotations: int = Field(45, ge=0)
    rotation_s: float = Field(2.0, gt=0)
    min_rotation_deg: float = Field(30.0, ge=0)
    max_rotation_deg: float = Field(120.0, gt=0)
    control: bool = Field(False, description="the second, independent recording (the control set)")


class ThermalParams(Params):
    """Rest while the die heats (warm-up), cools (start_C above the powered equilibrium) or restarts hot."""

    duration_s: float = Field(3600.0, gt=0)
    start_C: float | None = Field(None, description="die temperature at power-on; default ambient")
    ambient_C: float = 22.0
    swing_C: float = 0.0
    swing_period_s: float = Field(3600.0, gt=0)
    off_s: float = Field(0.0, ge=0, description="power off after duration_s (hot restart); 0 = none")
    restart_s: float = Field(1800.0, gt=0, description="recording after the restart")


class CooldownParams(ThermalParams):
    duration_s: float = 1800.0
    start_C: float | None = 60.0


class HotRestartParams(ThermalParams):
    duration_s: float = 1800.0
    off_s: float = 300.0


class TurntableParams(Params):
    turn_s: float = Field(20.0, gt=0)
    rest_s: float = Field(5.0, gt=0)


class FerrarisParams(Params):
    pose_s: float = Field(10.0, gt=0)
    turn_s: float = Field(10.0, gt=0)


class StandardParams(Params):
    """The default full session, short: warm-up, sphere path, references, move, turntable."""

    warmup_s: float = Field(300.0, ge=0)
    n_positions: int = Field(150, ge=10)
    rest_s: float = Field(5.0, gt=0)
    turn_s: float = Field(4.0, gt=0)
    max_turn_deg: float = Field(5.0, gt=0)
    path: Literal["steered", "walk"] = "steered"
    passes: int = Field(4, ge=1)
    reference_rest_s: float = Field(10.0, gt=0)
    move_m: float = Field(3.0, ge=0, description="carry the unit to the turntable; 0 = same place")
    turntable_turn_s: float = Field(20.0, gt=0)


def _sphere_rig(p: SphereRigParams, rng) -> Plan:
    b = Builder(attitude_with_up(EY, rng.uniform(0, 2 * np.pi)))
    if p.warmup_s:
        b.rest(p.warmup_s, "warmup")
    if p.n_turns:  # two-stage: random static positions first, then the gyro's small turns
        for _ in range(p.n_positions):
            b.goto(random_rotation(rng), 45 * DEG)
            b.rest(p.rest_s, "rest")
        small_turn_path(b, rng, p.n_turns, p.rest_s, p.turn_s, p.max_turn_deg, p.path, p.passes,
                        p.reposition_every)
    else:
        small_turn_path(b, rng, p.n_positions, p.rest_s, p.turn_s, p.max_turn_deg, p.path, p.passes,
                        p.reposition_every)
    references(b, rng, p.reference_rest_s, p.roll_turn_deg)
    return _plan(b)


def _gimbal(p: GimbalParams, rng) -> Plan:
    if p.control:
        rng = np.random.default_rng(rng.integers(1 << 62) + 1)
    b = Builder(attitude_with_up(EZ, 0.0))
    n_inner = round(360 / p.grid_deg)
    n_mid = round(180 / p.grid_deg) + 1
    for j in range(n_mid):
        for i in range(n_inner):
            b.rest(p.rest_s, "rest")
            if i < n_inner - 1:
                b.rotate(EZ, p.grid_deg * DEG, p.step_s, "grid_move")
        if j < n_mid - 1:
            b.rotate(EZ, p.grid_deg * DEG, p.step_s, "grid_move")
            b.rotate_world(EX, p.grid_deg * DEG, p.step_s, "grid_move")
    for _ in range(p.n_rotations):
        axis = rng.normal(size=3)
        angle = rng.uniform(p.min_rotation_deg, p.max_rotation_deg) * DEG * rng.choice([-1, 1])
        b.rotate(axis, angle, p.rotation_s, "gimbal_rotation")
        b.rest(p.rest_s, "rest")
    return _plan(b)


def _thermal(p: ThermalParams, rng) -> Plan:
    b = Builder(attitude_with_up(EY, rng.uniform(0, 2 * np.pi)))
    b.rest(p.duration_s, "warmup")
    windows = [(0.0, p.duration_s)]
    if p.off_s:
        b.rest(p.off_s, "power_off")
        b.rest(p.restart_s, "warmup")
        windows.append((p.duration_s + p.off_s, p.duration_s + p.off_s + p.restart_s))
    thermal = {"ambient_C": p.ambient_C, "swing_C": p.swing_C, "swing_period_s": p.swing_period_s,
               "initial_C": p.start_C}
    return Plan(b.build(), tuple(windows), thermal)


def _turntable(p: TurntableParams, rng) -> Plan:
    b = Builder(attitude_with_up(EZ, 0.0))
    turntable(b, [EZ, EX], p.turn_s, p.rest_s, rng)
    return _plan(b)


def _ferraris(p: FerrarisParams, rng) -> Plan:
    b = Builder(attitude_with_up(EX, 0.0))
    for axis in (EX, EY, EZ):
        b.goto(attitude_with_up(axis, rng.uniform(0, 2 * np.pi)))
        b.rest(p.pose_s, "pose")
        b.rotate(axis, 2 * np.pi, p.turn_s, "ferraris_turn")
        b.rest(p.pose_s, "pose")
        b.goto(attitude_with_up(-axis, rng.uniform(0, 2 * np.pi)))
        b.rest(p.pose_s, "pose")
    return _plan(b)


def _standard(p: StandardParams, rng) -> Plan:
    b = Builder(attitude_with_up(EY, rng.uniform(0, 2 * np.pi)))
    if p.warmup_s:
        b.rest(p.warmup_s, "warmup")
    small_turn_path(b, rng, p.n_positions, p.rest_s, p.turn_s, p.max_turn_deg, p.path, p.passes, 0)
    references(b, rng, p.reference_rest_s, 90.0)
    if p.move_m:
        b.translate([p.move_m, 0.0, 0.0], 6.0, "move")
    turntable(b, [EZ, EX], p.turntable_turn_s, 5.0, rng)
    return _plan(b)


def _plan(b: Builder) -> Plan:
    traj = b.build()
    return Plan(traj, ((0.0, traj.duration_s),), {})


PROTOCOLS: dict[str, tuple[type[Params], Callable[[Any, np.random.Generator], Plan]]] = {
    "standard": (StandardParams, _standard),
    "sphere_rig": (SphereRigParams, _sphere_rig),
    "sphere_rig_one_stage": (OneStageParams, _sphere_rig),
    "gimbal": (GimbalParams, _gimbal),
    "warmup": (ThermalParams, _thermal),
    "cooldown": (CooldownParams, _thermal),
    "cooldown_hot_restart": (HotRestartParams, _thermal),
    "turntable": (TurntableParams, _turntable),
    "ferraris": (FerrarisParams, _ferraris),
}


def protocol_params(name: str, **overrides: Any) -> Params:
    """The validated parameters of protocol ``name``; an error lists the known protocols/fields."""
    if name not in PROTOCOLS:
        raise ConfigError(f"unknown protocol {name!r}; known: {', '.join(PROTOCOLS)}")
    cls = PROTOCOLS[name][0]
    try:
        return cls(**overrides)
    except ValidationError as exc:
        raise ConfigError(f"protocol {name}: {describe_validation(exc, cls)}") from None


def build(name: str, params: Params, rng: np.random.Generator) -> Plan:
    return PROTOCOLS[name][1](params, rng)

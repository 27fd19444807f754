"""The simulator's chain: motion -> true inputs -> sensor model with effects -> raw samples.

Order (each stage lets the switched-on effects act, see ``imupipe.effects._base``):
timing, kinematics, die temperature, temperature read-out, true inputs, ``S x``,
bias, white noise, output (clipping), quantisation.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .environment import Environment
from .sensor import ImuModel, die_temperature
from .trajectory import Kinematics, Trajectory

SENSORS = ("accel", "gyro", "mag")
STAGES = ("timing", "temperature", "input", "sensed", "bias", "output")


@dataclass(frozen=True)
class SimContext:
    """What effects may read: the motion, environment, sensor model and the sample clock.

    ``t`` (n,) s from the first sample; ``t_on`` (n,) s since the last power-on;
    ``cycle`` (n,) int power-cycle index; ``kin`` the kinematics at ``t``.
    """

    trajectory: Trajectory
    env: Environment
    model: ImuModel
    t: np.ndarray
    t_on: np.ndarray
    cycle: np.ndarray
    windows: tuple[tuple[float, float], ...]
    kin: Kinematics


@dataclass(frozen=True)
class SimOutput:
    """Raw samples (n, 3) per triad, reported temperature (n,), and the hidden truth arrays."""

    t: np.ndarray
    raw: dict[str, np.ndarray]
    temperature: np.ndarray
    T_die: np.ndarray
    inputs: dict[str, np.ndarray]
    turn_on: dict[str, np.ndarray]  # (cycles, 3) per triad


def sample_times(windows: tuple[tuple[float, float], ...], rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample times (n,) s on each powered window's own grid, and the window index (n,)."""
    ts, cyc = [], []
    for i, (a, b) in enumerate(windows):
        n = int(np.floor((b - a) * rate_hz + 1e-9))
        ts.append(a + np.arange(n) / rate_hz)
        cyc.append(np.full(n, i))
    return np.concatenate(ts), np.concatenate(cyc)


def _rng(seed: int, *key: str) -> np.random.Generator:
    return np.random.default_rng([seed, *(zlib.crc32(k.encode()) for k in key)])


def run(trajectory: Trajectory, windows: tuple[tuple[float, float], ...], model: ImuModel, env: Environment,
        effects: Mapping[str, tuple[Any, Any]], seed: int) -> SimOutput:
    """Simulate the raw streams. ``effects``: identifier -> (effect object, validated params)."""
    t, cycle = sample_times(windows, model.rate_hz)
    t_on = t - np.array([w[0] for w in windows])[cycle]
    kin = trajectory.evaluate(t)
    ctx = SimContext(trajectory, env, model, t, t_on, cycle, tuple(windows), kin)
    streams: dict[str, Any] = {"t_accel": t.copy()}

    def stage(name: str) -> None:
        for ident, (effect, params) in effects.items():
            if effect.stage == name:
                effect.apply(streams, ctx, params, _rng(seed, "effect", ident))

    stage("timing")
    kin_a = kin if np.array_equal(streams["t_accel"], t) else trajectory.evaluate(streams["t_accel"])
    streams["T_die"] = die_temperature(model.thermal, t, list(windows))
    streams["T_reported"] = streams["T_die"].copy()
    stage("temperature")
    f_body = kin.specific_force(env.g)
    streams.update(accel=kin_a.specific_force(env.g), gyro=kin.omega.copy(), mag=kin.to_body(env.field_world),
                   accel_omega=kin_a.omega, accel_alpha=kin_a.alpha, f_body=f_body)
    stage("input")
    inputs = {s: streams[s].copy() for s in SENSORS}
    turn_on = {}
    for s in SENSORS:
        S, _, _ = model.triad(s).arrays()
        streams[s] = streams[s] @ S.T
    stage("sensed")
    for s in SENSORS:
        tm = model.triad(s)
        _, b0, k = tm.arrays()
        rng = _rng(seed, "sensor", s)
        turn_on[s] = rng.normal(0.0, tm.turn_on_sd, (len(windows), 3)) if tm.turn_on_sd else np.zeros((len(windows), 3))
        bias = b0 + turn_on[s][cycle] + np.outer(streams["T_die"] - 25.0, k)
        if tm.bias_rw:
            bias = bias + random_walk(t, cycle, np.full(3, tm.bias_rw), rng)
        if tm.bias_gm_sd:
            bias = bias + gauss_markov(t, tm.bias_gm_sd, tm.bias_gm_tau_s, rng)
        streams[s] = streams[s] + bias
    stage("bias")
    for s in SENSORS:
        sd = model.triad(s).noise_sd
        if sd:
            streams[s] = streams[s] + _rng(seed, "noise", s).normal(0.0, sd, streams[s].shape)
    stage("output")
    raw = {}
    for s in SENSORS:
        tm = model.triad(s)
        y = np.clip(streams[s], -tm.range, tm.range)
        raw[s] = quantise(y, tm.quantum)
    temperature = quantise(streams["T_reported"], model.thermal.readout_quantum_C)
    return SimOutput(t, raw, temperature, streams["T_die"], inputs, turn_on)


def quantise(y: np.ndarray, quantum: float) -> np.ndarray:
    return np.round(y / quantum) * quantum if quantum else y


def gauss_markov(t: np.ndarray, sd: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """A stationary first-order Gauss-Markov process (n, 3): steady-state ``sd``, correlation time
    ``tau_s`` (exact steps at the median sample interval; bias instability, not a walk)."""
    from scipy.signal import lfilter

    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    phi = np.exp(-dt / tau_s)
    n = rng.normal(size=(len(t), 3)) * sd * np.sqrt(1 - phi ** 2)
    n[0] = rng.normal(size=3) * sd  # the first sample from the steady state
    return lfilter([1.0], [1.0, -phi], n, axis=0)


def random_walk(t: np.ndarray, cycle: np.ndarray, sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A Wiener process (n, 3) with ``sigma`` (3,) per sqrt(s), starting at 0 at each power-on."""
    dt = np.diff(t, prepend=t[0])
    new = np.r_[True, cycle[1:] != cycle[:-1]]
    dt[new] = 0.0
    steps = rng.normal(size=(len(t), 3)) * np.sqrt(dt)[:, None] * sigma
    w = np.cumsum(steps, axis=0)
    start = np.maximum.accumulate(np.where(new, np.arange(len(t)), 0))
    return w - w[start] + steps[start]  # restart at each power-on (steps[start] is 0)

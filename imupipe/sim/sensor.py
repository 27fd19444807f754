"""The sensor model of one IMU: per-triad errors, noise, quantisation, range; die temperature.

Per triad (``spec/effects.md``, the forward model of ``imupipe.models``)::

    y = S x + b0 + c_p + k (T_die - 25) + w_bias(t) + n,    then clip to +-range, round to quantum

``x`` true input in the instrument frame, ``S`` (3, 3) scale/misalignment
(``M = inv(S)``), ``b0`` (3,) bias at 25 degC, ``c_p`` (3,) turn-on bias of power
cycle ``p`` (drawn per cycle), ``k`` (3,) per degC, ``w_bias`` a bias random walk
(``bias_rw`` per sqrt(s)), ``n`` white noise with ``noise_sd`` per sample.
Units: accel m/s^2, gyro rad/s, mag T.

Die temperature (first order): ``dT/dt = (T_amb(t) + P(t) dT_self - T) / tau``, P = 1
while powered; ``T_amb = ambient_C + swing_C sin(2 pi t / swing_period_s)``.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field, field_validator

from ..components import Params

G0 = 9.80665
DEG = np.pi / 180.0


def _matrix(v: object) -> list[list[float]]:
    a = np.asarray(v, dtype=float)
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"expected a finite 3x3 matrix, got shape {a.shape}")
    if abs(np.linalg.det(a)) < 1e-9:
        raise ValueError("S is singular")
    return a.tolist()


def _vector(v: object) -> list[float]:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"expected 3 finite numbers, got shape {a.shape}")
    return a.tolist()


class TriadModel(Params):
    """Errors and noise of one triad, SI units of the triad (see module docstring)."""

    S: list[list[float]] = Field(default_factory=lambda: np.eye(3).tolist())
    b0: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    k: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    noise_sd: float = Field(0.0, ge=0)
    bias_rw: float = Field(0.0, ge=0, description="bias random walk, units per sqrt(s)")
    bias_gm_sd: float = Field(0.0, ge=0, description="bias instability: a first-order Gauss-Markov "
                                                       "bias's steady-state sd, units")
    bias_gm_tau_s: float = Field(100.0, gt=0, description="its correlation time, s")
    turn_on_sd: float = Field(0.0, ge=0, description="turn-on bias repeatability per power cycle")
    quantum: float = Field(0.0, ge=0, description="least significant bit; 0 = no quantisation")
    range: float = Field(np.inf, gt=0, description="output clips at +-range")

    _m = field_validator("S")(classmethod(lambda cls, v: _matrix(v)))
    _v = field_validator("b0", "k")(classmethod(lambda cls, v: _vector(v)))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.array(self.S), np.array(self.b0), np.array(self.k)


class ThermalModel(Params):
    """Die temperature and its read-out."""

    ambient_C: float = 22.0
    self_heating_C: float = Field(20.0, ge=0)
    tau_s: float = Field(600.0, gt=0)
    initial_C: float | None = Field(None, description="die temperature at t = 0; default ambient")
    swing_C: float = 0.0
    swing_period_s: float = Field(3600.0, gt=0)
    readout_quantum_C: float = Field(1.0 / 256.0, ge=0)

    def ambient(self, t: np.ndarray) -> np.ndarray:
        return self.ambient_C + self.swing_C * np.sin(2 * np.pi * np.asarray(t) / self.swing_period_s)


class ImuModel(Params):
    """A whole IMU: sample rate, three triads, die temperature."""

    rate_hz: float = Field(100.0, gt=0)
    accel: TriadModel = TriadModel()
    gyro: TriadModel = TriadModel()
    mag: TriadModel = TriadModel()
    thermal: ThermalModel = ThermalModel()

    def triad(self, sensor: str) -> TriadModel:
        return getattr(self, sensor)


# consumer MEMS at 100 Hz: (noise per sample, bias scale, k scale, turn-on sd, LSB, range)
_DEFAULTS = {
    "accel": {"noise_sd": 0.5e-3 * G0, "bias": 30e-3 * G0, "k": 0.2e-3 * G0, "turn_on_sd": 1e-3 * G0,
                  "quantum": 16 * G0 / 65536, "range": 8 * G0, "scale": 0.03, "mis": 0.01},
    "gyro": {"noise_sd": 0.02 * DEG, "bias": 1.0 * DEG, "k": 0.01 * DEG, "turn_on_sd": 0.05 * DEG,
                 "quantum": 1000 * DEG / 65536, "range": 500 * DEG, "scale": 0.02, "mis": 0.01},
    "mag": {"noise_sd": 0.3e-6, "bias": 20e-6, "k": 0.02e-6, "turn_on_sd": 0.0,
                "quantum": 0.15e-6, "range": 4.9e-3, "scale": 0.05, "mis": 0.02},
}


def default_triad(sensor: str, rng: np.random.Generator) -> TriadModel:
    """Realistic consumer-MEMS errors drawn from ``rng``: scale errors of a few %, misalignment ~1e-2,
    biases of tens of mg / ~1 deg/s / tens of uT, and the noise, resolution and range of such a part."""
    d = _DEFAULTS[sensor]
    S = np.diag(1 + rng.uniform(-d["scale"], d["scale"], 3))
    S += (1 - np.eye(3)) * rng.normal(0, d["mis"], (3, 3))
    return TriadModel(
        S=S.tolist(), b0=rng.uniform(-d["bias"], d["bias"], 3).tolist(),
        k=rng.uniform(-d["k"], d["k"], 3).tolist(), noise_sd=d["noise_sd"], turn_on_sd=d["turn_on_sd"],
        quantum=d["quantum"], range=d["range"],
    )


def default_imu(rng: np.random.Generator, **overrides) -> ImuModel:
    """An ``ImuModel`` with errors drawn by ``default_triad``; ``overrides`` replace whole fields."""
    fields = {s: default_triad(s, rng) for s in ("accel", "gyro", "mag")}
    fields.update(overrides)
    return ImuModel(**fields)


def die_temperature(thermal: ThermalModel, t: np.ndarray, windows: list[tuple[float, float]],
                    step_s: float = 1.0) -> np.ndarray:
    """Die temperature (n,) degC at sorted times ``t`` (n,) s, powered inside ``windows``.

    Exact first-order response to an input linear between grid points (first-order hold);
    the grid is the sample times plus power edges, with at most ``step_s`` between points.
    """
    t = np.asarray(t, dtype=float)
    t_end = max(t[-1], windows[-1][1]) if len(t) else windows[-1][1]
    filler = np.arange(0.0, t_end + step_s, step_s)
    edges = [e for w in windows for e in w]
    grid = np.unique(np.concatenate([t, filler, edges, [0.0]]))
    T = np.empty(len(grid))
    T[0] = thermal.ambient_C if thermal.initial_C is None else thermal.initial_C
    mid = 0.5 * (grid[1:] + grid[:-1])
    powered = np.zeros(len(mid), bool)
    for a, b in windows:
        powered |= (mid >= a) & (mid < b)
    heat = np.where(powered, thermal.self_heating_C, 0.0)
    u0 = thermal.ambient(grid[:-1]) + heat
    u1 = thermal.ambient(grid[1:]) + heat
    h = np.diff(grid)
    e = np.exp(-h / thermal.tau_s)
    ramp = thermal.tau_s * (u1 - u0) / h
    for i in range(len(h)):  # T_{i+1} = u1 - tau du/h + (T_i - u0 + tau du/h) e
        T[i + 1] = u1[i] - ramp[i] + (T[i] - u0[i] + ramp[i]) * e[i]
    return np.interp(t, grid, T)


def first_order_lag(t: np.ndarray, u: np.ndarray, tau_s: float) -> np.ndarray:
    """Exact first-order lag (time constant ``tau_s``) of ``u`` (n,) linear between samples ``t`` (n,)."""
    y = np.empty_like(u, dtype=float)
    if len(u) == 0:
        return y
    y[0] = u[0]
    h = np.diff(t)
    e = np.exp(-h / tau_s)
    ramp = tau_s * np.diff(u) / np.where(h > 0, h, 1.0)
    for i in range(len(h)):
        y[i + 1] = u[i + 1] - ramp[i] + (y[i] - u[i] + ramp[i]) * e[i]
    return y

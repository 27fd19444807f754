"""An estimated calibration against the simulator's truth: gauge-free errors with units.

A calibration is defined only up to the choice of the instrument frame: any
rotation ``Q`` of the estimate's frame is as good as the truth's. So each triad's
correction is compared through ``M_est S_true`` (identity when exact), split by
the polar decomposition ``M_est S_true = Q H`` (``Q`` a rotation, ``H`` symmetric
positive definite):

- ``frame_deg``: the angle of ``Q``, the estimate's frame against the truth's;
- ``shape_ppm``: max |H - I|, every error of the triad but its frame;
- ``scale_ppm``: max |diag(H - I)|; ``nonorth_ppm``: max off-diagonal of ``H - I``
  (``H`` is symmetric: this is the symmetric part of the error);
- ``overall_scale_ppm``: ``det(H)^(1/3) - 1``; ``shape_scale_aside_ppm``: max
  |H / det(H)^(1/3) - I|. A magnetometer calibrated without ``field_T`` knows the
  field only up to its nominal scale: its ``shape_scale_aside_ppm`` is the meaningful one;
- ``bias``: max |b0_est - b0_true| over axes (accel mg, gyro deg/s, mag uT);
  ``k``: max |k_est - k_true| (the same unit per degC).

Between triads, ``gyro_accel_align_deg`` is the angle of ``Q_acc^T Q_gyro``: how far the
gyro's axes are turned against the accelerometer's (the frame itself is free). To first
order in small errors, ``Q = I + skew(E)`` and ``H = I + sym(E)`` with ``E = M_est S_true - I``.
Derivation and use: ``docs/simulator.md``, "Comparing with truth".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np

from ..models import Calibration, TriadCalibration
from ..rotations import angle_between, nearest_rotation, rotation_angle

STANDARD_GRAVITY = 9.80665  # m/s^2: what "mg" means here unless told otherwise
BIAS_UNITS = {"accel": "mg", "gyro": "deg/s", "mag": "uT"}


def bias_factor(sensor: str, g_m_s2: float = STANDARD_GRAVITY) -> float:
    """Multiplier from the triad's SI unit to ``BIAS_UNITS[sensor]``."""
    return {"accel": 1e3 / g_m_s2, "gyro": 180.0 / np.pi, "mag": 1e6}[sensor]


@dataclass(frozen=True)
class TriadErrors:
    """One triad's gauge-free errors (see the module docstring); ``Q`` (3, 3) is the frame rotation."""

    sensor: str
    frame_deg: float
    shape_ppm: float
    scale_ppm: float
    nonorth_ppm: float
    overall_scale_ppm: float
    shape_scale_aside_ppm: float
    bias: float
    k: float
    Q: np.ndarray

    @property
    def bias_unit(self) -> str:
        return BIAS_UNITS[self.sensor]


@dataclass(frozen=True)
class CalibrationErrors:
    """Errors of every triad present in both calibrations, and the gyro-to-accel alignment
    (deg; None unless both triads are there)."""

    triads: Mapping[str, TriadErrors]
    gyro_accel_align_deg: float | None

    def __getitem__(self, sensor: str) -> TriadErrors:
        return self.triads[sensor]

    def as_dict(self) -> dict[str, float]:
        """Flat ``{"accel_scale_ppm": ..., "gyro_bias_deg_s": ..., "gyro_accel_align_deg": ...}``."""
        out: dict[str, float] = {}
        for sensor, e in self.triads.items():
            unit = e.bias_unit.replace("/", "_")
            for name, value in asdict(e).items():
                if name in ("sensor", "Q"):
                    continue
                key = {"bias": f"bias_{unit}", "k": f"k_{unit}_per_C"}.get(name, name)
                out[f"{sensor}_{key}"] = float(value)
        if self.gyro_accel_align_deg is not None:
            out["gyro_accel_align_deg"] = self.gyro_accel_align_deg
        return out


def frame_and_shape(M_est: np.ndarray, S_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polar decomposition ``M_est S_true = Q H``: rotation ``Q`` (3, 3), shape ``H`` (3, 3)."""
    A = np.asarray(M_est, float) @ np.asarray(S_true, float)
    Q = nearest_rotation(A)
    return Q, Q.T @ A


def triad_errors(estimate: TriadCalibration, truth: TriadCalibration,
                 g_m_s2: float = STANDARD_GRAVITY) -> TriadErrors:
    """Errors of ``estimate`` against ``truth`` (same sensor); ``g_m_s2`` defines the mg."""
    Q, H = frame_and_shape(estimate.M, truth.S)
    E = 0.5 * (H + H.T) - np.eye(3)  # symmetric already, up to rounding (or a mirrored axis)
    off = E[~np.eye(3, dtype=bool)]
    scale = np.cbrt(np.linalg.det(H))
    unit = bias_factor(estimate.sensor, g_m_s2)
    return TriadErrors(
        sensor=estimate.sensor,
        frame_deg=float(np.degrees(rotation_angle(Q))),
        shape_ppm=float(np.abs(H - np.eye(3)).max() * 1e6),
        scale_ppm=float(np.abs(np.diag(E)).max() * 1e6),
        nonorth_ppm=float(np.abs(off).max() * 1e6),
        overall_scale_ppm=float((scale - 1.0) * 1e6),
        shape_scale_aside_ppm=float(np.abs(H / scale - np.eye(3)).max() * 1e6),
        bias=float(np.abs(estimate.b0 - truth.b0).max() * unit),
        k=float(np.abs(estimate.k - truth.k).max() * unit),
        Q=Q,
    )


def calibration_errors(estimate: Calibration | Mapping[str, TriadCalibration],
                       truth: Calibration | Mapping[str, TriadCalibration],
                       g_m_s2: float = STANDARD_GRAVITY) -> CalibrationErrors:
    """Errors of every triad in both ``estimate`` and ``truth`` (``Calibration`` or
    ``{sensor: TriadCalibration}``), and the gyro-to-accel alignment."""
    est = estimate.triads if isinstance(estimate, Calibration) else estimate
    tru = truth.triads if isinstance(truth, Calibration) else truth
    triads = {s: triad_errors(est[s], tru[s], g_m_s2) for s in ("accel", "gyro", "mag")
              if s in est and s in tru}
    align = None
    if "accel" in triads and "gyro" in triads:
        align = float(np.degrees(angle_between(triads["accel"].Q, triads["gyro"].Q)))
    return CalibrationErrors(triads, align)


def reported_sigma(estimate: TriadCalibration, g_m_s2: float = STANDARD_GRAVITY) -> dict[str, float]:
    """The estimate's own 1-sigma (``details`` ``sigma_M``, ``sigma_b0``, ``sigma_k``) in the
    units of ``TriadErrors``: ``scale_ppm`` max over the diagonal of ``sigma_M``,
    ``nonorth_ppm`` and ``frame_deg`` max over its off-diagonal, ``shape_ppm`` max over all,
    ``bias`` and ``k`` max over axes. Valid to first order (``M_est S_true`` near I). Keys
    whose detail is missing are left out."""
    d = estimate.details
    out: dict[str, float] = {}
    if "sigma_M" in d:
        s = np.asarray(d["sigma_M"], float)
        off = s[~np.eye(3, dtype=bool)].max()
        out.update(scale_ppm=float(np.diag(s).max() * 1e6), nonorth_ppm=float(off * 1e6),
                   shape_ppm=float(s.max() * 1e6), frame_deg=float(np.degrees(off)))
    unit = bias_factor(estimate.sensor, g_m_s2)
    for key, name in (("sigma_b0", "bias"), ("sigma_k", "k")):
        if key in d:
            out[name] = float(np.max(d[key]) * unit)
    return out

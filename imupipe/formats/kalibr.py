"""Kalibr ``imu.yaml`` (``kalibr_imu.yaml``): noise densities, random walks, topic, rate, intrinsics.

Kalibr's IMU configuration (wiki "IMU Noise Model and Intrinsics"; ``imu.yaml`` of
``kalibr_calibrate_imu_camera``) holds continuous-time noise, one number per sensor:

    accelerometer_noise_density  m/s^2/sqrt(Hz)    accelerometer_random_walk  m/s^3/sqrt(Hz)
    gyroscope_noise_density      rad/s/sqrt(Hz)    gyroscope_random_walk      rad/s^2/sqrt(Hz)
    rostopic, update_rate [Hz] (for discretisation: sigma_d = sigma_c sqrt(update_rate))

Noise comes, by preference, from a table of schema ``noise`` (a noise stage: per
sensor and axis ``noise_density``, ``random_walk``, ``rate_hz``, in raw units);
otherwise from what the calibration holds: each triad's white per-sample sigma
of the rests (``details.noise.white_sigma``), made continuous with
``sigma_c = sigma_d / sqrt(rate)``, and the gyro bias random walk of the joint
fit (``details.noise.bias_random_walk``, already continuous). Per-axis raw
figures go through ``M`` to the corrected output (``sqrt(sum_j M_ij^2 s_j^2)``,
axes independent); Kalibr's single number is the largest axis. A figure nothing
gives (the accelerometer random walk without a noise stage) is written ``null``
with a comment: Kalibr then refuses the file until it is filled in.

Intrinsics, in the layout Kalibr writes its own results in
(``IccScaledMisalignedImu``, model ``scale-misalignment``)::

    accel_measured = M_a a_i + b_a                          M_a lower triangular
    gyro_measured  = M_g C_gyro_i w_i + A (C_gyro_i a_i) + b_g   M_g lower triangular

From imupipe's forward model ``y = M^-1 x + b``: ``M^-1 = M_a Q`` (lower-triangular
times orthogonal), Kalibr's IMU frame ``i`` is imupipe's instrument frame turned
by ``Q`` (``x_i = Q x``, written as ``imupipe.C_i_imupipe``); the gyro's
``M_gyro^-1 Q^T = M_g C_gyro_i`` the same way; ``A = 0`` (imupipe has no
g-sensitivity). Kalibr estimates biases as random walks: ``b0``/``k`` are not
held (written under ``imupipe:`` for reference). Axes are as recorded: Kalibr
reads the IMU messages in the bag as they are.
"""

from __future__ import annotations

import numpy as np

from ..models import UNITS
from ._common import FormatExporter, Notes, Source, header, num

FILE = "kalibr_imu.yaml"
FIELDS = {"accel": ("accelerometer_noise_density", "accelerometer_random_walk"),
          "gyro": ("gyroscope_noise_density", "gyroscope_random_walk")}
UNITS_C = {"accel": ("m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)"), "gyro": ("rad/s/sqrt(Hz)",
                                                                  "rad/s^2/sqrt(Hz)")}


def lower_rq(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``S = L Q``: ``L`` lower triangular with positive diagonal when ``det S > 0``, ``Q`` a
    rotation (``det S < 0`` leaves ``L`` with negative diagonal and ``Q`` proper)."""
    q, r = np.linalg.qr(S.T)  # S^T = q r  ->  S = r^T q^T
    L, Q = r.T, q.T
    D = np.diag(np.sign(np.diag(L)))
    L, Q = L @ D, D @ Q
    if np.linalg.det(Q) < 0:
        L, Q = -L, -Q
    return L, Q


def through_M(M: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Per-axis sigma of ``M y`` for independent per-axis sigma ``sigma`` of ``y``."""
    return np.sqrt((M**2) @ (np.asarray(sigma, float) ** 2))


def raw_noise(source: Source, sensor: str, notes: Notes) -> tuple[np.ndarray | None,
                                                                   np.ndarray | None]:
    """(noise density (3,), random walk (3,)) in raw units, continuous time; None when unknown."""
    if source.noise is not None:
        rows = [r for r in source.noise.to_pylist() if r.get("sensor") == sensor]
        by_axis = {r["axis"]: r for r in rows}
        if set(by_axis) == {"x", "y", "z"}:
            notes.say(f"{sensor}: noise density and random walk from the noise stage's table")
            return (np.array([by_axis[a]["noise_density"] for a in "xyz"], float),
                    np.array([by_axis[a]["random_walk"] for a in "xyz"], float))
    noise = dict(source.calibration[sensor].details.get("noise") or {})
    rate = source.rate_hz(sensor)
    density = None
    if "white_sigma" in noise and rate:
        density = np.asarray(noise["white_sigma"], float) / np.sqrt(rate)
        notes.say(f"{sensor}: noise density = white per-sample sigma of the rests / "
                  f"sqrt({rate:.6g} Hz) (sigma_c = sigma_d / sqrt(rate))")
    walk = None
    if "bias_random_walk" in noise:
        walk = np.asarray(noise["bias_random_walk"], float)
        notes.say(f"{sensor}: random walk = the joint fit's {sensor} bias random walk (continuous)")
    return density, walk


class KalibrExporter(FormatExporter):
    name = "kalibr"
    target = "Kalibr (kalibr_calibrate_imu_camera --imu)"
    files = (FILE,)

    def render(self, source: Source) -> dict[str, str]:
        notes, body = Notes("kalibr", source.session), []
        for sensor in ("accel", "gyro"):
            if sensor not in source.triads:
                notes.drop(f"no {sensor} calibration: Kalibr's {FIELDS[sensor][0]} and "
                           f"{FIELDS[sensor][1]} are written null")
                body += [f"{FIELDS[sensor][0]}: null", f"{FIELDS[sensor][1]}: null"]
                continue
            M = source.calibration[sensor].M
            density, walk = raw_noise(source, sensor, notes)
            for field, unit, value in zip(FIELDS[sensor], UNITS_C[sensor], (density, walk),
                                          strict=True):
                if value is None or not np.any(value > 0):
                    why = "not estimated" if value is None else "estimated as 0 (none detected)"
                    notes.drop(f"{field}: {why} by this pipeline; Kalibr needs a positive "
                               "value: add a noise stage (Allan deviation) or take it from the "
                               "datasheet")
                    body.append(f"{field}: null  # [{unit}] fill in before running Kalibr")
                    continue
                per_axis = through_M(M, value)
                body.append(f"{field}: {num(per_axis.max())}  # [{unit}] largest axis of "
                            f"{', '.join(f'{v:.4g}' for v in per_axis)} (x, y, z)")
        topic = next((source.facts.get(s, {}).get("topic") for s in ("accel", "gyro")
                      if source.facts.get(s, {}).get("topic")), None)
        if topic is None:
            notes.drop("the recording names no ROS topic: rostopic is written as /imu0, set it "
                       "to your IMU's topic")
        rate = source.rate_hz("accel") or source.rate_hz("gyro")
        body += [f"rostopic: {topic or '/imu0'}",
                 f"update_rate: {num(rate) if rate else 'null'}  # [Hz] median sample rate"]
        body += self._intrinsics(source, notes)
        lines = header("Kalibr IMU configuration", self.target, source) + notes.comment() + body
        return {FILE: "\n".join(lines) + "\n"}

    def _intrinsics(self, source: Source, notes: Notes) -> list[str]:
        if any(source.raw_unit(s) != UNITS[s] for s in ("accel", "gyro") if s in source.triads):
            notes.drop("intrinsics: raw values are not in SI units, while Kalibr's M maps SI "
                       "inputs to the measured SI values; not written")
            return []
        tri = source.triads
        Q = np.eye(3)
        out = ["model: scale-misalignment  # Kalibr's layout for its own results"]
        if "accel" in tri:
            L, Q = lower_rq(np.linalg.inv(tri["accel"].M))
            out += ["accelerometers:", f"  M: {_matrix(L)}"]
        if "gyro" in tri:
            L, C = lower_rq(np.linalg.inv(tri["gyro"].M) @ Q.T)
            out += ["gyroscopes:", f"  M: {_matrix(L)}", f"  A: {_matrix(np.zeros((3, 3)))}",
                    f"  C_gyro_i: {_matrix(C)}"]
        notes.say("intrinsics: inv(M) = M_kalibr Q (Q a rotation); Kalibr's IMU frame is "
                  "imupipe's turned by Q: x_i = C_i_imupipe x; A = 0")
        out += ["imupipe:  # not read by Kalibr", f"  C_i_imupipe: {_matrix(Q)}"]
        for s, t in tri.items():
            if s in FIELDS:
                out += [(f"  {s}_b0: [{', '.join(num(v) for v in t.b0)}]  # [{UNITS[s]}] at "
                        f"{t.T_ref_C:g} degC"),
                        f"  {s}_k: [{', '.join(num(v) for v in t.k)}]  # [{UNITS[s]}/degC]"]
                notes.drop(f"{s} bias b0 and k: Kalibr estimates biases itself as random walks "
                           "(kept under imupipe: for reference)")
        return out


def _matrix(A: np.ndarray) -> str:
    return "[" + ", ".join("[" + ", ".join(num(v) for v in row) + "]" for row in A) + "]"


COMPONENTS = [KalibrExporter()]

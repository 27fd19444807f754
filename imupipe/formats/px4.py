"""PX4 parameters (``px4.params``): ``CAL_ACCn_*``, ``CAL_GYROn_*``, ``CAL_MAGn_*``, ``TC_*``.

PX4's corrections (``src/lib/sensor_calibration``, ``Correct()``), applied to
``sensor_accel``/``sensor_gyro``/``sensor_mag`` in the board's FRD axes before
the board rotation::

    accel = R ((y - thermal - CAL_ACCn_{X,Y,Z}OFF) .* CAL_ACCn_{X,Y,Z}SCALE)     m/s^2
    gyro  = R (y - thermal - CAL_GYROn_{X,Y,Z}OFF)                              rad/s
    mag   = R (S (y - CAL_MAGn_{X,Y,Z}OFF)),  S = [[XSCALE, XODIAG, YODIAG],
                                                  [XODIAG, YSCALE, ZODIAG],
                                                  [YODIAG, ZODIAG, ZSCALE]]     gauss

``thermal`` (``src/modules/temperature_compensation``, ``calc_thermal_offsets_3D``)
is ``X0 + X1 dT + X2 dT^2 + X3 dT^3`` per axis with ``dT = T - TC_xn_TREF``, T
clamped to ``[TC_xn_TMIN, TC_xn_TMAX]``, when ``TC_A_ENABLE``/``TC_G_ENABLE`` is
1. Calibrations are matched to sensors by ``CAL_ACCn_ID`` / ``TC_An_ID`` = the
driver's device id (a ULog's ``sensor_accel.device_id``).

From imupipe (after FRD): offsets = ``b0``; accel scales = ``diag(M)``
(off-diagonal terms are not held); the gyro has no scale in PX4 (``M`` not
held); mag ``S = M`` when ``M`` is symmetric, else the symmetric factor of
``M = U P`` (the rotation ``U`` is not held), offsets in gauss. When ``k`` is
nonzero, ``TC_*`` carry imupipe's thermal model as PX4's cubic exactly:
``TREF = 25``, ``X0 = 0``, ``X1 = k``, ``X2 = X3 = 0`` (imupipe's model is
linear), ``TMIN``/``TMAX`` the session's temperature range, outside which PX4
holds the offset constant. The file is QGroundControl's ``.params`` layout
(tab-separated ``vehicle component name value type``; type 6 int32, 9 float),
as PX4's own ``process_sensor_data.py`` writes it. PX4 stores float32.
"""

from __future__ import annotations

import numpy as np

from ..models import TriadCalibration
from ._common import FormatExporter, Notes, Source, cross_axis, header, num, symmetric_part_held

FILE = "px4.params"
GAUSS_PER_T = 1e4
INT32, REAL32 = 6, 9
SHORT = {"accel": "ACC", "gyro": "GYRO", "mag": "MAG"}
TC_SHORT = {"accel": "A", "gyro": "G"}


class Params:
    """Rows of a QGroundControl parameter file."""

    def __init__(self):
        self.rows: list[tuple[str, str, int]] = []

    def add(self, name: str, value: float, kind: int = REAL32) -> None:
        self.rows.append((name, str(int(value)) if kind == INT32 else num(value), kind))

    def xyz(self, fmt: str, values: np.ndarray) -> None:
        for axis, v in zip("XYZ", values, strict=True):
            self.add(fmt.format(axis=axis), v)

    def lines(self) -> list[str]:
        return [f"1\t1\t{name}\t{value}\t{kind}" for name, value, kind in self.rows]


def _device_id(source: Source, sensor: str, name: str, notes: Notes) -> int:
    device_id = source.facts.get(sensor, {}).get("device_id")
    if device_id is None:
        notes.drop(f"{name}: the recording does not give the {sensor}'s PX4 device id; written "
                   "as 0, which PX4 matches to no sensor: set it to the device id "
                   f"(`listener sensor_{'accel' if sensor == 'accel' else sensor}` on the vehicle)")
        return 0
    return int(device_id)


def _thermal(params: Params, source: Source, sensor: str, n: int, t: TriadCalibration,
             notes: Notes) -> None:
    """TC_{A,G}n_* carrying ``b(T) - b0 = k (T - T_ref)`` as PX4's cubic."""
    short, k = TC_SHORT[sensor], t.k
    span = source.temperature_range()
    if span is None:
        notes.drop(f"{sensor} k = {k.tolist()}: the session's temperature range is unknown, "
                   "so no TC_ parameters were written")
        return
    params.add(f"TC_{short}_ENABLE", 1, INT32)
    params.add(f"TC_{short}{n}_ID", _device_id(source, sensor, f"TC_{short}{n}_ID", notes), INT32)
    params.add(f"TC_{short}{n}_TREF", t.T_ref_C)
    params.add(f"TC_{short}{n}_TMIN", span[0])
    params.add(f"TC_{short}{n}_TMAX", span[1])
    for order, coeffs in ((0, np.zeros(3)), (1, k), (2, np.zeros(3)), (3, np.zeros(3))):
        for axis, c in enumerate(coeffs):
            params.add(f"TC_{short}{n}_X{order}_{axis}", c)
    notes.say(f"{sensor}: TC_{short}{n}: X1 = k, X0 = X2 = X3 = 0, TREF = {t.T_ref_C:g} (imupipe's linear "
              f"model as PX4's cubic); valid {span[0]:.2f} to {span[1]:.2f} degC, the session's "
              "range: PX4 holds the offset constant outside it")


def render_params(source: Source, notes: Notes) -> Params:
    source.require_si("PX4", "PX4's CAL_ parameters correct the driver's SI output")
    params, n = Params(), source.instance()
    notes.say(f"slot n = {n} (the device name's instance); PX4 finds a calibration by its _ID")
    for sensor in source.triads:
        t = source.in_frame(sensor, "FRD", notes)
        cal = f"CAL_{SHORT[sensor]}{n}"
        params.add(f"{cal}_ID", _device_id(source, sensor, f"{cal}_ID", notes), INT32)
        if sensor == "mag":
            P = symmetric_part_held(t.M, "PX4's", notes)
            params.xyz(f"{cal}_{{axis}}OFF", t.b0 * GAUSS_PER_T)
            params.xyz(f"{cal}_{{axis}}SCALE", np.diag(P))
            params.xyz(f"{cal}_{{axis}}ODIAG", [P[0, 1], P[0, 2], P[1, 2]])
            notes.say("mag: offsets in gauss (1 T = 1e4 gauss); S = the symmetric M")
            if np.any(t.k != 0):
                notes.drop(f"mag bias temperature coefficient k = {t.k.tolist()} T/degC: not "
                           "written (PX4's TC_M application is not covered by this exporter)")
            continue
        params.xyz(f"{cal}_{{axis}}OFF", t.b0)
        if sensor == "accel":
            params.xyz(f"{cal}_{{axis}}SCALE", np.diag(t.M))
            if cross_axis(t.M) > 0:
                notes.drop(f"accel cross-axis terms of M (largest {cross_axis(t.M):.3g} of the "
                           "diagonal): PX4's accelerometer scale is diagonal; written diag(M)")
        else:
            dev = float(np.abs(t.M - np.eye(3)).max())
            if dev > 0:
                notes.drop(f"gyro scale and misalignment M (largest |M - I| entry {dev:.3g}): "
                           "PX4 has no gyroscope scale; only the offsets are written")
        if np.any(t.k != 0):
            _thermal(params, source, sensor, n, t, notes)
    notes.say("offsets = b0 (bias at 25 degC) in m/s^2, rad/s; values are doubles in this "
              "file, PX4 keeps float32 (relative rounding ~6e-8)")
    return params


class Px4Exporter(FormatExporter):
    name = "px4"
    target = "PX4 (QGroundControl: Parameters > Tools > Load from file)"
    files = (FILE,)

    def render(self, source: Source) -> dict[str, str]:
        notes = Notes("px4", source.session)
        params = render_params(source, notes)
        lines = ["# Onboard parameters for Vehicle 1", "#",
                 *header("PX4 parameters", self.target, source), *notes.comment(), "#",
                 "# Vehicle-Id Component-Id Name Value Type", *params.lines()]
        return {FILE: "\n".join(lines) + "\n"}


COMPONENTS = [Px4Exporter()]

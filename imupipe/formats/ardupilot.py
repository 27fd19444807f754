"""ArduPilot parameters (``ardupilot.param``): ``INS_ACCOFFS``/``ACCSCAL``, ``INS_GYROFFS``,
``COMPASS_OFS``/``DIA``/``ODI``.

ArduPilot's corrections, in the board's FRD axes:

- accel (``AP_InertialSensor_Backend::_rotate_and_correct_accel``, ArduPilot 4.x:
  the sensor-orientation rotation first, then offsets, then scaling)::

      accel = (y - INS_ACCOFFS) .* INS_ACCSCAL                 m/s^2

- gyro (``_rotate_and_correct_gyro``): ``gyro = y - INS_GYROFFS``  rad/s, no scale.
- compass (``AP_Compass_Backend::correct_field``; offsets are *added*)::

      mag = D (y + COMPASS_OFS),  D = [[DIA_X, ODI_X, ODI_Y],
                                       [ODI_X, DIA_Y, ODI_Z],
                                       [ODI_Y, ODI_Z, DIA_Z]]   milligauss

Instance n (0-based) is ``INS_ACC``/``INS_ACC2``/``INS_ACC3``,
``INS_GYR``/``INS_GYR2``/``INS_GYR3``, ``COMPASS_``/``COMPASS_..2``/``..3``.
From imupipe (after FRD): ``INS_ACCOFFS = b0``, ``INS_ACCSCAL = diag(M)``
(cross-axis terms not held), ``INS_GYROFFS = b0`` (gyro ``M`` not held),
``COMPASS_OFS = -b0`` in milligauss (1 T = 1e7 mG), ``D = M`` when symmetric, else
the symmetric factor ``P`` of ``M = U P`` (``U`` not held). ArduPilot's own
temperature calibration (``INS_TCALn_*``) is not written: a nonzero ``k`` is
reported. The file is Mission Planner's / MAVProxy's ``NAME,VALUE`` layout.
"""

from __future__ import annotations

import numpy as np

from ._common import FormatExporter, Notes, Source, cross_axis, header, num, symmetric_part_held

FILE = "ardupilot.param"
MILLIGAUSS_PER_T = 1e7


def names(sensor: str, n: int) -> dict[str, str]:
    """Parameter name prefixes of instance ``n`` (0-based), with ``{axis}`` for X/Y/Z."""
    i = "" if n == 0 else str(n + 1)
    if sensor == "accel":
        return {"offset": f"INS_ACC{i}OFFS_{{axis}}", "scale": f"INS_ACC{i}SCAL_{{axis}}"}
    if sensor == "gyro":
        return {"offset": f"INS_GYR{i}OFFS_{{axis}}" if i else "INS_GYROFFS_{axis}"}
    return {"offset": f"COMPASS_OFS{i}_{{axis}}", "diagonal": f"COMPASS_DIA{i}_{{axis}}",
            "off_diagonal": f"COMPASS_ODI{i}_{{axis}}"}


class ArduPilotExporter(FormatExporter):
    name = "ardupilot"
    target = "ArduPilot (Mission Planner / MAVProxy parameter file)"
    files = (FILE,)

    def render(self, source: Source) -> dict[str, str]:
        source.require_si("ArduPilot", "ArduPilot's INS_/COMPASS_ parameters correct the "
                          "driver's SI output")
        notes, rows, n = Notes("ardupilot", source.session), [], source.instance()
        notes.say(f"instance n = {n} (the device name's); ArduPilot numbers its second and third "
                  "sensors ACC2/GYR2/OFS2, ...")

        def xyz(fmt: str, values) -> None:
            rows.extend(f"{fmt.format(axis=a)},{num(v)}" for a, v in zip("XYZ", values, strict=True))

        for sensor in source.triads:
            t = source.in_frame(sensor, "FRD", notes)
            name = names(sensor, n)
            if sensor == "accel":
                xyz(name["offset"], t.b0)
                xyz(name["scale"], np.diag(t.M))
                if cross_axis(t.M) > 0:
                    notes.drop(f"accel cross-axis terms of M (largest {cross_axis(t.M):.3g} of the "
                               "diagonal): INS_ACCSCAL is diagonal; written diag(M)")
            elif sensor == "gyro":
                xyz(name["offset"], t.b0)
                dev = float(np.abs(t.M - np.eye(3)).max())
                if dev > 0:
                    notes.drop(f"gyro scale and misalignment M (largest |M - I| entry {dev:.3g}): "
                               "ArduPilot has no gyroscope scale; only INS_GYROFFS is written")
            else:
                D = symmetric_part_held(t.M, "ArduPilot's", notes)
                xyz(name["offset"], -t.b0 * MILLIGAUSS_PER_T)
                xyz(name["diagonal"], np.diag(D))
                xyz(name["off_diagonal"], [D[0, 1], D[0, 2], D[1, 2]])
                notes.say("compass: COMPASS_OFS = -b0 in milligauss (ArduPilot adds its offsets)")
            if np.any(t.k != 0):
                notes.drop(f"{sensor} bias temperature coefficient k = {t.k.tolist()} per degC: "
                           "ArduPilot's INS_TCAL polynomials are not written; the offsets are "
                           f"the biases at {t.T_ref_C:g} degC")
        notes.say("accel/gyro offsets = b0 (bias at 25 degC) in m/s^2, rad/s")
        lines = header("ArduPilot parameters", self.target, source) + notes.comment() + rows
        return {FILE: "\n".join(lines) + "\n"}


COMPONENTS = [ArduPilotExporter()]

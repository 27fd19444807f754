"""ROS ``imu_calib`` YAML (``imu_calib.yaml``): the accelerometer calibration ``apply_calib`` loads.

imu_calib's model (``src/accel_calib/accel_calib.cpp``, ``AccelCalib::applyCalib``)::

    corrected = SM raw - bias        SM: 9 numbers row-major, bias after the matrix

applied to ``sensor_msgs/Imu.linear_acceleration`` [m/s^2] in the message's
frame (ROS, REP-103: FLU). From imupipe: ``SM = M``, ``bias = M b0``. imu_calib
holds no temperature term and no gyroscope or magnetometer calibration
(``apply_calib`` only estimates a gyro bias at start-up): those are reported.
"""

from __future__ import annotations

import numpy as np

from ._common import ExportError, FormatExporter, Notes, Source, header, num

FILE = "imu_calib.yaml"


class ImuCalibExporter(FormatExporter):
    name = "imu_calib"
    target = "ROS imu_calib (apply_calib, AccelCalib::loadCalib)"
    files = (FILE,)

    def render(self, source: Source) -> dict[str, str]:
        source.require_si("imu_calib", "imu_calib corrects sensor_msgs/Imu data in m/s^2")
        if "accel" not in source.triads:
            raise ExportError(f"{source.session}: cannot export to imu_calib: it holds an "
                              "accelerometer calibration and this one has none")
        notes = Notes("imu_calib", source.session)
        a = source.in_frame("accel", "FLU", notes)
        bias = a.M @ a.b0
        notes.say("SM = M; bias = M b0 (imu_calib subtracts its bias after the matrix)")
        if np.any(a.k != 0):
            notes.drop(f"accel bias temperature coefficient k = {a.k.tolist()} m/s^2/degC: "
                       f"imu_calib has no temperature term; bias is the one at {a.T_ref_C:g} degC")
        for sensor in ("gyro", "mag"):
            if sensor in source.triads:
                notes.drop(f"the {sensor} calibration: imu_calib calibrates the accelerometer "
                           "only (apply_calib estimates a gyro bias at start-up)")
        lines = header("imu_calib calibration", self.target, source) + notes.comment()
        lines += [f"SM: [{', '.join(num(v) for v in a.M.ravel())}]",
                  f"bias: [{', '.join(num(v) for v in bias)}]"]
        return {FILE: "\n".join(lines) + "\n"}


COMPONENTS = [ImuCalibExporter()]

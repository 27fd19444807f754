"""imu_tk ``.calib`` files: one per triad (``imu_tk_acc.calib``, ``imu_tk_gyro.calib``, ...).

imu_tk's model (``include/imu_tk/calibration.h``, ``CalibratedTriad_``)::

    X' = T K (X - B)     T misalignment (unit diagonal), K = diag(scale), B bias

``load()`` reads 9 numbers (T, row-major), 9 (K, row-major) and 3 (B), whitespace
separated, and stops: the comment block goes after them, where imu_tk never
reads. imu_tk has no units of its own, so any raw unit (counts too) is fine.

From imupipe: ``K = diag(M_11, M_22, M_33)``, ``T = M K^-1`` (unit diagonal), so
``T K = M`` exactly; ``B = b0``, the bias at 25 degC. imu_tk has no temperature
term: a nonzero ``k`` is reported as not held.
"""

from __future__ import annotations

import numpy as np

from ..models import UNITS
from ._common import FormatExporter, Notes, Source, header, num

FILES = {"accel": "imu_tk_acc.calib", "gyro": "imu_tk_gyro.calib", "mag": "imu_tk_mag.calib"}


def _rows(A: np.ndarray) -> list[str]:
    return [" ".join(num(v) for v in row) for row in np.atleast_2d(A)]


def triad_text(source: Source, sensor: str) -> str:
    notes = Notes("imu_tk", source.session)
    triad = source.in_frame(sensor, None, notes)
    K = np.diag(np.diag(triad.M))
    T = triad.M @ np.diag(1.0 / np.diag(triad.M))
    notes.say(f"K = diag(M), T = M K^-1 (unit diagonal): T K = M exactly; B = b0 (bias at "
              f"{triad.T_ref_C:g} degC) in {source.raw_unit(sensor)}")
    if np.any(triad.k != 0):
        notes.drop(f"{sensor} bias temperature coefficient k = {triad.k.tolist()} "
                   f"{source.raw_unit(sensor)}/degC: imu_tk has no temperature term; B is the "
                   f"bias at {triad.T_ref_C:g} degC")
    lines = [*_rows(T), "", *_rows(K), "", *_rows(triad.b0.reshape(3, 1)), "", ""]
    lines += header("imu_tk CalibratedTriad", "imu_tk CalibratedTriad_::load "
                    "(X' = T K (X - B))", source)
    lines += [(f"# {sensor}: raw unit {source.raw_unit(sensor)}, T K maps it to "
              f"{UNITS[sensor]}"), *notes.comment()]
    return "\n".join(lines) + "\n"


class ImuTkExporter(FormatExporter):
    name = "imu_tk"
    target = "imu_tk (CalibratedTriad_::load)"
    files = tuple(FILES.values())

    def render(self, source: Source) -> dict[str, str]:
        return {FILES[s]: triad_text(source, s) for s in source.triads}


COMPONENTS = [ImuTkExporter()]

"""A hand's tremor on a simulated recording: holds that are not still, as hand-held rests are.

Not an effect of the catalogue (it is not omitted physics of the sensor, it is motion of the
support): a post-process of the streams, for testing what sees rests.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa

G0 = 9.80665


def add_tremor(streams: Mapping[str, pa.Table], rng: np.random.Generator, gyro_dps: float = 1.0,
               accel_mg: float = 5.0, band_hz: tuple[float, float] = (4.0, 8.0), tones: int = 2) -> dict:
    """``streams`` with ``tones`` sinusoids of frequencies drawn in ``band_hz`` on random axes and
    phases added to gyro (amplitude ``gyro_dps`` deg/s each) and accel (``accel_mg`` mg each),
    over the whole session. Other streams pass through."""
    out = dict(streams)
    for sensor, amp in (("gyro", np.radians(gyro_dps)), ("accel", accel_mg * 1e-3 * G0)):
        t = streams[sensor]
        t_ns = t.column("t_ns").to_numpy()
        ts = (t_ns - t_ns[0]) * 1e-9
        add = np.zeros((len(ts), 3))
        for _ in range(tones):
            f, ph = rng.uniform(*band_hz), rng.uniform(0, 2 * np.pi)
            u = rng.normal(size=3)
            add += amp * np.outer(np.sin(2 * np.pi * f * ts + ph), u / np.linalg.norm(u))
        out[sensor] = with_added(t, add)
    return out


def with_added(table: pa.Table, add: np.ndarray) -> pa.Table:
    """``table`` (a triad's stream) with ``add`` (n, 3) added to its x, y, z."""
    for i, c in enumerate("xyz"):
        table = table.set_column(table.column_names.index(c), c, pa.array(table.column(c).to_numpy() + add[:, i]))
    return table

"""Where the session happens: gravity, the geomagnetic field and Earth's rate in the world frame.

World frame ENU (x east, y north, z up). Gravity points down, so the specific
force of a unit at rest is ``(0, 0, +g)``. The field points north and, in the
northern hemisphere, down by the dip angle: ``B = F (0, cos dip, -sin dip)``
(declination folded into the heading: magnetic north is the y axis). Earth's
rate is ``Omega (0, cos lat, sin lat)``. Defaults: Moscow (the sphere-rig paper:
dip 71.4 deg, eq. 3 gives B = (0.319, -0.948, 0) in its Y-up frame).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..components import Params

EARTH_RATE_RAD_S = 7.292115e-5


def normal_gravity(latitude_deg: float, height_m: float = 0.0) -> float:
    """WGS-84 normal gravity (Somigliana) at ``latitude_deg``, m/s^2, with a free-air height term."""
    s2 = np.sin(np.radians(latitude_deg)) ** 2
    g0 = 9.7803253359 * (1 + 0.00193185265241 * s2) / np.sqrt(1 - 0.00669437999013 * s2)
    return float(g0 - 3.086e-6 * height_m)


class Environment(Params):
    """Local gravity, field and latitude. ``gravity_m_s2 = None`` uses normal gravity at the latitude."""

    latitude_deg: float = Field(55.75, ge=-90, le=90)
    height_m: float = 150.0
    gravity_m_s2: float | None = Field(None, gt=0)
    field_T: float = Field(50e-6, gt=0)
    dip_deg: float = Field(71.4, ge=-90, le=90)

    @property
    def g(self) -> float:
        return self.gravity_m_s2 if self.gravity_m_s2 is not None else normal_gravity(self.latitude_deg, self.height_m)

    @property
    def gravity_world(self) -> np.ndarray:
        """Acceleration of gravity (3,), m/s^2, ENU."""
        return np.array([0.0, 0.0, -self.g])

    @property
    def field_world(self) -> np.ndarray:
        """Geomagnetic field (3,), T, ENU."""
        d = np.radians(self.dip_deg)
        return self.field_T * np.array([0.0, np.cos(d), -np.sin(d)])

    def earth_rate_world(self, latitude_deg: float | None = None) -> np.ndarray:
        """Earth's angular rate (3,), rad/s, ENU."""
        lat = np.radians(self.latitude_deg if latitude_deg is None else latitude_deg)
        return EARTH_RATE_RAD_S * np.array([0.0, np.cos(lat), np.sin(lat)])

    def summary(self) -> dict:
        return {**self.model_dump(), "g_m_s2": self.g, "gravity_world": self.gravity_world.tolist(),
                "field_world_T": self.field_world.tolist(), "frame": "ENU"}

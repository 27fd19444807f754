"""Params: the validated parameters of stages and solvers (pydantic models), and the field types
that refuse a unit slip. ``imupipe.components`` hands them out on first use: ``imupipe ingest``
registers readers only, and importing pydantic is a tenth of that command."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict


class Params(BaseModel):
    """Base for every params object: frozen, unknown keys rejected. Each model's validator is
    built when it first validates (``defer_build``): registering the stages and solvers defines
    ~37 models, of which imu_tk's pipeline validates 8 (~13 ms of its run)."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)


class NoParams(Params):
    pass


GRAVITY_RANGE_M_S2 = (9.7, 9.9)  # Earth's surface: 9.76 (equatorial peaks) to 9.84 (poles)
FIELD_RANGE_T = (1e-7, 1e-3)  # Earth's field is 25-65 uT; 1 mT is 20 times the strongest


def _in_range(lo: float, hi: float, what: str, fix: str):
    def check(value: float) -> float:
        if not lo <= value <= hi:
            raise ValueError(f"{value:g} is not {what} ({lo:g} to {hi:g}): a unit slip? {fix}")
        return value
    return check


LocalGravity = Annotated[float, AfterValidator(_in_range(
    *GRAVITY_RANGE_M_S2, "a local gravity in m/s^2", "give it in m/s^2, e.g. 9.80665"))]
"""A params field of local gravity, m/s^2, refused outside Earth's range (``g_m_s2 = 98.1``)."""
FieldStrength = Annotated[float, AfterValidator(_in_range(
    *FIELD_RANGE_T, "a geomagnetic field in tesla", "give it in T, e.g. 50e-6 for 50 uT"))]
"""A params field of magnetic field strength, T, refused when it reads as uT or gauss."""

"""Stage ``screen_events``: refuse streams in the wrong unit; find gaps, shocks and splices,
and keep the turns that hold one out of every fit.

Runs after the segmentation. First the magnitudes of the raw streams are checked
against their SI names (``check_units``): an accelerometer whose median ``|a|`` is
about 1 is in g, not m/s^2; a gyro reaching hundreds is in deg/s; a magnetometer
of tens is in uT. Such a session is refused (one line naming the unit and the fix),
unless its reader declared the raw unit (``unit = "counts"`` in a manifest).

Then ``imupipe.diagnosis.events.detect`` finds gaps in the stamps, one-sample
shocks and splices (gravity jumping between two samples with no rotation measured).
A turn whose motion holds one cannot be integrated: it is dropped from the
``turns`` output (a warning names how many and why), and the events table goes to
the residual map and the verdict.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import schemas
from ..columns import kept_rows
from ..components import BoundSolver, Params, Stage
from ..diagnosis import events as ev
from ..errors import ReaderError
from .segment import xyz

RAW_UNIT_KEY = b"imupipe.raw_unit"  # set by readers that leave values unconverted (counts)
EXCLUDING = ("gap", "shock", "splice")

# (low, high) of the median magnitude of a stream in SI, and what other ranges mean
UNIT_CHECKS = {
    "accel": ((4.0, 25.0), [((0.7, 1.4), "g"), ((700.0, 1400.0), "mg"), ((70.0, 140.0), "cm/s^2 or dm/s^2")],
              "m/s^2", 'give the column unit = "g" in a session manifest, or multiply by 9.80665'),
    "mag": ((2e-6, 5e-4), [((5.0, 150.0), "uT"), ((0.05, 1.5), "gauss"), ((50.0, 1500.0), "mG"),
                           ((5e3, 1.5e5), "nT")],
            "T", 'give the column unit (e.g. unit = "uT") in a session manifest'),
    "temperature": ((-60.0, 150.0), [((213.0, 423.0), "kelvin")], "degC",
                    'give unit = "K" in a session manifest, or subtract 273.15'),
}
GYRO_MAX_RAD_S = 40.0  # above any MEMS gyro's range (2000 deg/s = 34.9 rad/s)


class ScreenParams(Params):
    """``check_units``: refuse streams whose magnitudes contradict their SI unit;
    ``gap_factor``/``gap_min_s``: a stamp interval longer than both (in nominal intervals,
    in s) is a gap; ``shock_accel_m_s2``/``shock_gyro_rad_s``: one sample this far from both
    neighbours is a shock; ``splice_min_deg``: smaller gravity jumps are not judged;
    ``leave_out_turns``: drop the turns holding a gap, shock or splice from ``turns``."""

    check_units: bool = True
    gap_factor: float = Field(ev.GAP_FACTOR, gt=1)
    gap_min_s: float = Field(ev.GAP_MIN_S, ge=0)
    shock_accel_m_s2: float = Field(ev.SHOCK_ACCEL_M_S2, gt=0)
    shock_gyro_rad_s: float = Field(ev.SHOCK_GYRO_RAD_S, gt=0)
    splice_min_deg: float = Field(ev.SPLICE_MIN_DEG, gt=0, le=180)
    leave_out_turns: bool = True
    """False: the turns pass unchanged (a pipeline whose turns come from elsewhere, e.g.
    ferraris' sections); the events still reach the verdict."""


def _raw_unit(table: pa.Table) -> str | None:
    raw = (table.schema.metadata or {}).get(RAW_UNIT_KEY)
    return raw.decode() if raw else None


def check_units(tables: Mapping[str, pa.Table]) -> None:
    """Raise ``ReaderError`` naming the likely unit when a stream's magnitudes contradict SI."""
    for sensor, table in tables.items():
        if table is None or table.num_rows == 0 or _raw_unit(table):
            continue
        if sensor == "temperature":
            values = table.column("temperature").to_numpy().astype(float)
        else:
            values = np.linalg.norm(xyz(table)[1], axis=1)
        values = values[np.isfinite(values)]
        if not len(values):
            continue
        if sensor == "gyro":
            top = float(np.quantile(values, 0.99))
            if top > GYRO_MAX_RAD_S:
                raise ReaderError(
                    f"gyro: rates reach {top:.4g} (99th percentile of |omega|), beyond any MEMS gyro's "
                    f"range in rad/s ({GYRO_MAX_RAD_S:g}): the data look like deg/s (or counts); give the "
                    'column unit = "deg/s" (or "counts") in a session manifest, or multiply by pi/180')
            continue
        if sensor not in UNIT_CHECKS:
            continue
        (lo, hi), others, si, fix = UNIT_CHECKS[sensor]
        med = float(np.median(values))
        if lo <= med <= hi:
            continue
        guess = next((name for (a, b), name in others if a <= med <= b), None)
        what = "|value|" if sensor != "temperature" else "value"
        looks = f"the data look like {guess}" if guess else f"not {si}"
        raise ReaderError(f"{sensor}: median {what} is {med:.4g}, expected {lo:g} to {hi:g} {si}: "
                          f"{looks}; {fix}")


def screen(inputs: Mapping[str, pa.Table], params: ScreenParams, solver: BoundSolver | None) -> dict:
    if params.check_units:
        check_units({s: inputs.get(s) for s in ("accel", "gyro", "mag", "temperature")})
    turns = inputs["turns"]
    t0 = int((turns.schema.metadata or {}).get(b"imupipe.t0_ns", b"0"))
    streams, shock = {}, {}
    for sensor in ("accel", "gyro"):
        t_ns, y = xyz(inputs[sensor])
        streams[sensor] = ((t_ns - t0) * 1e-9, y)
        if not _raw_unit(inputs[sensor]):  # thresholds are in SI
            shock[sensor] = params.shock_accel_m_s2 if sensor == "accel" else params.shock_gyro_rad_s
    found = ev.detect(streams, gap_factor=params.gap_factor, gap_min_s=params.gap_min_s, shock=shock,
                      splice_min_deg=params.splice_min_deg)
    t_start = (turns.column("t_start_ns").to_numpy() - t0) * 1e-9
    t_end = (turns.column("t_end_ns").to_numpy() - t0) * 1e-9
    bad = np.zeros(turns.num_rows, bool)
    why: dict[str, int] = {}
    for e in found if params.leave_out_turns else ():
        if e.kind in EXCLUDING:
            hit = (t_start <= e.window[1]) & (t_end >= e.window[0]) & ~bad
            if hit.any():
                why[e.kind] = why.get(e.kind, 0) + int(hit.sum())
            bad |= hit
    if bad.any():
        warnings.warn(f"{int(bad.sum())} of {len(bad)} turns left out of the fits: they hold "
                      + ", ".join(f"{n} {k}{'s' if n > 1 else ''}" for k, n in why.items())
                      + " (see the events of the residual map / the verdict)", stacklevel=2)
    kept = kept_rows(turns, ~bad)
    cols = {name: kept.column(name) for name in kept.column_names}
    cols["index"] = pa.array(np.arange(kept.num_rows, dtype=np.int64))
    kept = schemas.stamp(pa.table(cols, metadata=turns.schema.metadata), "turns")
    table = pa.table({
        "kind": pa.array([e.kind for e in found], pa.string()),
        "sensor": pa.array([e.sensor for e in found], pa.string()),
        "t_start_s": pa.array([e.window[0] for e in found], pa.float64()),
        "t_end_s": pa.array([e.window[1] for e in found], pa.float64()),
        "detail": pa.array([e.detail for e in found], pa.string()),
    })
    meta = {"imupipe.t0_ns": str(t0), "imupipe.turns_left_out": str(int(bad.sum())),
            "imupipe.turns": str(len(bad))}
    return {"events": schemas.stamp(table, "events", meta), "turns": kept}


STAGE = Stage(
    name="screen_events", version="2", func=screen,
    inputs={"accel": "accel", "gyro": "gyro", "mag": "mag", "temperature": "temperature",
            "turns": "turns"},
    outputs={"events": "events", "turns": "turns"}, params=ScreenParams,
    optional_inputs=frozenset({"mag", "temperature"}),
    description="refuse streams in the wrong unit; gaps, shocks and splices found; the turns "
                "holding one left out",
)
COMPONENTS = [STAGE]

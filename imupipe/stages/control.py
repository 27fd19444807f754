"""Validation B (Chikrin & Golousov 2021): judge a calibration on a control set.

The paper records two sessions, fits on the first and checks on the second: the
gravity measured at the rest before each turn, carried through the turn by the
integrated gyro, must match the gravity measured after it. Here the control
set is held-out turns of the same session (``split_control``) or the rests and
turns of a second session wired to ``validate_control``; the error per turn is
the angle between predicted and measured gravity, before and after calibration.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import schemas
from ..columns import kept_rows
from ..components import Params, Stage
from ..models import Calibration, TriadCalibration
from ..observations import Rests, Turns
from ..rotations import carry, pad_turns, rotation_angle, turn_rotations


def control_errors(accel: TriadCalibration, gyro: TriadCalibration, rests: Rests,
                   turns: Turns) -> tuple[np.ndarray, np.ndarray]:
    """Per turn (m,): gravity mismatch angle (rad) and the turn's rotation angle (rad).

    Gravity at each rest is the corrected accelerometer mean (thermal term
    included when the rests have temperatures); the gyro is corrected sample
    by sample and integrated exactly.
    """
    T = rests.temperature
    T = np.where(np.isfinite(T), T, accel.T_ref_C)
    g = accel.apply(rests.need("accel"), T)
    g = g / np.linalg.norm(g, axis=1, keepdims=True)
    rate, dt = pad_turns(turns.t, turns.gyro)
    T_turn = 0.5 * (T[turns.before] + T[turns.after])
    corrected = (rate - gyro.bias(T_turn)[:, None, :]) @ gyro.M.T
    R = turn_rotations(corrected * (dt[..., None] > 0), dt)
    predicted = carry(R, g[turns.before])  # Eq. (2.16)
    cos = np.clip(np.sum(predicted * g[turns.after], axis=1), -1.0, 1.0)
    return np.arccos(cos), rotation_angle(R)


def error_table(cal: Calibration, rests: Rests, turns: Turns) -> pa.Table:
    """The ``control_errors`` table for a calibration with accel and gyro rows."""
    accel, gyro = cal["accel"], cal["gyro"]
    err_after, rot = control_errors(accel, gyro, rests, turns)
    nominal_a = TriadCalibration("accel", np.eye(3))
    err_before, _ = control_errors(nominal_a, TriadCalibration("gyro", np.eye(3)), rests, turns)
    bias = rests.need("gyro").mean(axis=0)
    err_bias, _ = control_errors(nominal_a, TriadCalibration("gyro", np.eye(3), bias), rests, turns)
    table = pa.table({
        "turn": np.arange(len(turns), dtype=np.int64),
        "rest_before": np.asarray(turns.before, dtype=np.int64),
        "rest_after": np.asarray(turns.after, dtype=np.int64),
        "t_start_s": np.array([t[0] if len(t) else np.nan for t in turns.t]),
        "rotation_deg": np.degrees(rot),
        "error_before_deg": np.degrees(err_before),
        "error_bias_only_deg": np.degrees(err_bias),
        "error_after_deg": np.degrees(err_after),
    })
    summary = {
        "imupipe.rms_before_deg": _rms(np.degrees(err_before)),
        "imupipe.rms_after_deg": _rms(np.degrees(err_after)),
    }
    return schemas.stamp(table, "control_errors", summary)


def _rms(x: np.ndarray) -> str:
    return repr(float(np.sqrt(np.mean(x**2)))) if len(x) else "nan"


# --------------------------------------------------------------------------- split


class SplitParams(Params):
    mode: Literal["interleaved", "time"] = "interleaved"
    """interleaved: every ``every``-th turn is held out (rests shared); time: the last
    ``fraction`` of the session (rests and turns) is the control set."""
    every: int = Field(4, ge=2)
    fraction: float = Field(0.3, gt=0, lt=1)


def split_control(inputs: Mapping[str, pa.Table], params: SplitParams, solver=None) -> dict[str, pa.Table]:
    rests_t, turns_t = inputs["rests"], inputs["turns"]
    m = turns_t.num_rows
    if params.mode == "interleaved":
        control = (np.arange(m) % params.every) == params.every - 1
        return {"rests": rests_t, "turns": _turn_rows(turns_t, ~control, None),
                "control_rests": rests_t, "control_turns": _turn_rows(turns_t, control, None)}
    rests = Rests.from_table(rests_t)
    t_cut = rests.t_start_s[0] + (1 - params.fraction) * (rests.t_end_s[-1] - rests.t_start_s[0])
    cal_rest = rests.t_end_s <= t_cut
    before = turns_t.column("rest_before").to_numpy()
    after = turns_t.column("rest_after").to_numpy()
    out = {}
    for prefix, keep in (("", cal_rest), ("control_", ~cal_rest)):
        new_index = np.full(len(rests), -1)
        new_index[keep] = np.arange(int(keep.sum()))
        rows = keep[before] & keep[after]
        out[f"{prefix}rests"] = rests.subset(keep).to_table()
        out[f"{prefix}turns"] = _turn_rows(turns_t, rows, new_index)
    return out


def _turn_rows(turns: pa.Table, rows: np.ndarray, new_index: np.ndarray | None) -> pa.Table:
    """The turns at ``rows`` renumbered, rest indices mapped through ``new_index``."""
    sub = kept_rows(turns, rows)
    cols = {name: sub.column(name) for name in sub.column_names}
    cols["index"] = pa.array(np.arange(sub.num_rows, dtype=np.int64))
    if new_index is not None:
        for c in ("rest_before", "rest_after"):
            cols[c] = pa.array(new_index[sub.column(c).to_numpy()].astype(np.int64))
    table = pa.table(cols, metadata=turns.schema.metadata)
    return schemas.stamp(table, "turns")


# --------------------------------------------------------------------------- validate


def validate_control(inputs: Mapping[str, pa.Table], params: Params, solver=None) -> dict[str, pa.Table]:
    cal = Calibration.from_tables(inputs["accel_calibration"], inputs["gyro_calibration"])
    rests = Rests.from_table(inputs["rests"])
    turns = Turns.from_tables(inputs["turns"], inputs["gyro"], rests.t0_ns)
    return {"control": error_table(cal, rests, turns)}


SPLIT = Stage(
    name="split_control",
    version="1",
    func=split_control,
    inputs={"rests": "rests", "turns": "turns"},
    outputs={"rests": "rests", "turns": "turns", "control_rests": "rests", "control_turns": "turns"},
    params=SplitParams,
    description="Hold out a control set of turns (or the end of the session) for validate_control.",
)

VALIDATE = Stage(
    name="validate_control",
    version="1",
    func=validate_control,
    inputs={"rests": "rests", "turns": "turns", "gyro": "gyro",
            "accel_calibration": "calibration", "gyro_calibration": "calibration"},
    outputs={"control": "control_errors"},
    description="Control-set error (method B): angle between the gravity predicted through each "
                "turn by the calibrated gyro and the gravity measured after it, before and after.",
)

COMPONENTS = [SPLIT, VALIDATE]

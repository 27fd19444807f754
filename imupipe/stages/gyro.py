"""Gyroscope calibration from rests and the turns between them (method A: eqs. 26-37).

Gravity at each rest comes from the calibrated accelerometer, so the gyro ends up
in the accelerometer's instrument frame. With the thermal stage wired, the rest
means and the turns' rates are handed to the solver with ``k (T - 25)`` removed
(a turn at the mean temperature of its two rests), so the bias the solver returns,
by whatever rule it has, is the bias at T_ref.
Residuals test the exported calibration (its forward model): per rest, the measured
gyro mean vs ``cal.bias(T)``; per turn, gravity after the turn vs gravity before
rotated by the gyro corrected with ``cal.M`` and ``cal.bias(T)`` (T of the turn: the
mean of its two rests), not by the rests' own means.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from ..components import BoundSolver, Params, Stage
from ..errors import ConfigError
from ..models import triads_to_table
from ..observations import GyroObservations, Rests, Turns
from ..rotations import carry, hold_intervals, ragged_turn_rotations
from ._calib_common import (
    add_thermal_variance,
    concat_residuals,
    dT,
    model_T,
    need_triad,
    noise_details,
    residual_table,
    thermal_k,
)


class GyroParams(Params):
    """``roll_turn``: index of the paper's scale turn (eq. 37) into the segmentation's turns
    table (before ``max_turn_s``), None: scale from all turns;
    ``roll_turn_time_s``: or a time inside it (s since the session start);
    ``detect_roll_turn``: otherwise take a turn from instrument Y up to Z down (corrected
    gravity within ``detect_tol_deg`` of +Y before and -Z after, eq. 37), if there is one;
    ``max_turn_s``: motions longer than this (e.g. a carry to the turntable) are left out."""

    roll_turn: int | None = Field(None, ge=0)
    roll_turn_time_s: float | None = None
    detect_roll_turn: bool = False
    detect_tol_deg: float = Field(5.0, gt=0, le=90)
    max_turn_s: float = Field(30.0, gt=0)
    solver: str = "gyro_rodrigues"
    solver_params: dict = Field(default_factory=dict)


def rest_gravity(inputs: Mapping[str, pa.Table], rests: Rests, stage: str) -> np.ndarray:
    """(n, 3) unit gravity per rest from the calibrated accelerometer."""
    acc = need_triad(inputs, "accel", "accel", stage)
    g = acc.apply(rests.need("accel"), model_T(rests.temperature))
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def find_roll_turn(turns: Turns, gravity: np.ndarray, tol_deg: float) -> int | None:
    """The turn from instrument Y up to Z down (the paper's scale turn), or None."""
    cos_tol = np.cos(np.radians(tol_deg))
    for j in range(len(turns)):
        g0, g1 = gravity[turns.before[j]], gravity[turns.after[j]]
        if g0[1] >= cos_tol and -g1[2] >= cos_tol:
            return j
    return None


def turn_subset(turns: Turns, p: GyroParams, gravity: np.ndarray) -> tuple[Turns, int | None]:
    keep = np.array([len(t) > 1 and (t[-1] - t[0]) <= p.max_turn_s for t in turns.t], dtype=bool)
    roll = p.roll_turn
    if roll is not None and roll >= len(turns):
        raise ConfigError(f"calibrate_gyro: roll_turn = {roll} but the segmentation found "
                          f"{len(turns)} turns (valid indices 0..{len(turns) - 1}); check the "
                          "turns table or use roll_turn_time_s")
    if roll is None and p.roll_turn_time_s is not None:
        inside = [j for j, t in enumerate(turns.t) if len(t) and t[0] <= p.roll_turn_time_s <= t[-1]]
        roll = inside[0] if inside else None
    if roll is None and p.detect_roll_turn:
        roll = find_roll_turn(turns, gravity, p.detect_tol_deg)
    if roll is not None:
        keep[roll] = True
        roll = int(np.cumsum(keep)[roll] - 1)
    return turns.subset(keep), roll


def calibrate_gyro(inputs: Mapping[str, pa.Table], params: GyroParams, solver: BoundSolver | None):
    rests = Rests.from_table(inputs["rests"])
    gravity = rest_gravity(inputs, rests, "calibrate_gyro")
    turns, roll = turn_subset(Turns.from_tables(inputs["turns"], inputs["gyro"], rests.t0_ns), params,
                              gravity)
    bias = rests.need("gyro")
    a = rests.need("accel")
    gravity_cov = rests.cov_of_mean("accel") / np.sum(a * a, axis=1)[:, None, None]
    k, sigma_k = thermal_k(inputs, "gyro")
    obs = GyroObservations(gravity, bias - np.outer(dT(rests.temperature), k),
                           rests.cov_of_mean("gyro"), without_thermal(turns, rests.temperature, k),
                           rests.temperature, roll, gravity_cov, rests.white_sigma("gyro"))
    fit = add_thermal_variance(solver.solve(obs), rests.temperature, sigma_k)
    cal = fit.to_calibration("gyro", solver.solver.name, k=k, sigma_k=sigma_k, extra={
        "noise": noise_details(rests, "gyro"), "roll_turn": roll,
    })
    mid = 0.5 * (rests.t_start_s + rests.t_end_s)
    sigma = np.sqrt(np.diagonal(rests.cov_of_mean("gyro"), axis1=1, axis2=2))
    res_rest = residual_table("calibrate_gyro", "gyro", "rest", mid, rests.temperature, bias,
                              cal.bias(model_T(rests.temperature)), sigma)
    # per turn: gravity after vs gravity before carried through the calibrated rotation
    T_turn = model_T(0.5 * (rests.temperature[turns.before] + rests.temperature[turns.after]))
    g0, g1 = gravity[turns.before], gravity[turns.after]
    pred = carry(ragged_turn_rotations(turns.t, turns.gyro, hold_intervals, cal.bias(T_turn), cal.M), g0)
    res_turn = residual_table("calibrate_gyro", "gyro", "turn",
                              np.array([0.5 * (t[0] + t[-1]) for t in turns.t]),
                              np.full(len(turns), np.nan), g1, pred, None)
    return {"calibration": triads_to_table([cal]), "residuals": concat_residuals([res_rest, res_turn])}


def without_thermal(turns: Turns, T: np.ndarray, k: np.ndarray) -> Turns:
    """``turns`` with ``k (T - 25)`` removed from the rates, each turn at the mean temperature
    of its two rests ``T`` (n,) degC; the turns themselves when ``k`` is zero."""
    if not np.any(k):
        return turns
    d = 0.5 * (dT(T)[turns.before] + dT(T)[turns.after])
    return Turns(turns.before, turns.after, turns.t,
                 tuple(w - di * k for w, di in zip(turns.gyro, d, strict=True)))


STAGE = Stage(
    name="calibrate_gyro", version="3", func=calibrate_gyro,
    inputs={"rests": "rests", "turns": "turns", "gyro": "gyro", "accel": "calibration",
            "thermal": "calibration"},
    outputs={"calibration": "calibration", "residuals": "residuals"}, params=GyroParams,
    optional_inputs=frozenset({"thermal"}), solver_kind="gyro",
    description="gyroscope M, b0 from turns between rests, in the accelerometer's frame",
)
COMPONENTS = [STAGE]

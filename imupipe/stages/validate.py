"""Turn validation of method A: Rodrigues error (eq. 38) and turn-angle error (eq. 39).

For every turn, before calibration (raw accel directions, raw gyro minus the
rests' bias, identity M) and after (the exported accel and gyro calibrations: the
gyro corrected with its ``M`` and ``bias(T)`` at the turn's temperature, the forward
model, not the rests' own means). A turn is
informative when it tilts gravity by at least ``min_tilt_deg`` (eq. 39 divides
by ``|e x (g1 + g0)|``); it is accepted when its angle error after calibration
is below ``tolerance_deg`` (the paper: 0.1 deg). The verdict and RMS values are
in the table's ``imupipe.summary`` metadata. Validating on the turns used for the
fit is in-sample; wire a second session's tables for an independent check.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import schemas
from ..components import BoundSolver, Params, Stage
from ..models import TriadCalibration
from ..observations import Rests, Turns
from ..rotations import carry, hold_intervals, quat_to_matrix, ragged_turn_quaternions
from ..solvers.gyro_rodrigues import angle_error, rodrigues_error
from ._calib_common import model_T, need_triad


class ValidateParams(Params):
    """``tolerance_deg``: acceptance of the turn-angle error; ``min_tilt_deg``: smaller
    gravity tilts make eq. (39) undefined; ``max_turn_deg``: larger turns (repositioning,
    turntable) are reported but not judged."""

    tolerance_deg: float = Field(0.1, gt=0)
    min_tilt_deg: float = Field(0.5, ge=0, le=180)
    max_turn_deg: float = Field(60.0, gt=0)


def turn_errors(rests: Rests, turns: Turns, acc: TriadCalibration | None,
                gyr: TriadCalibration | None) -> tuple[np.ndarray, ...]:
    """Per turn: Gibbs vectors Y (m, 3), |E| (m,), angle error (m,) rad, tilt (m,) rad,
    gravity error (m,) rad (gravity before carried by the gyro vs gravity after)."""
    a = rests.need("accel")
    g = acc.apply(a, model_T(rests.temperature)) if acc is not None else a
    g = g / np.linalg.norm(g, axis=1, keepdims=True)
    w = rests.need("gyro")
    if gyr is not None:
        T = rests.temperature
        M, bias = gyr.M, gyr.bias(model_T(0.5 * (T[turns.before] + T[turns.after])))
    else:
        M, bias = np.eye(3), 0.5 * (w[turns.before] + w[turns.after])
    q = ragged_turn_quaternions(turns.t, turns.gyro, hold_intervals, bias, M)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    Y = q[:, 1:] / np.where(np.abs(q[:, :1]) > 1e-12, q[:, :1], 1e-12)  # e tan(chi/2)
    g0, g1 = g[turns.before], g[turns.after]
    E = np.linalg.norm(rodrigues_error(g0, g1, Y), axis=1)
    eps = angle_error(g0, g1, Y)
    tilt = np.arccos(np.clip(np.sum(g0 * g1, axis=1), -1, 1))
    carried = carry(quat_to_matrix(q), g0)
    grav = np.arctan2(np.linalg.norm(np.cross(carried, g1), axis=1), np.sum(carried * g1, axis=1))
    return Y, E, eps, tilt, grav


def validate(inputs: Mapping[str, pa.Table], params: ValidateParams, solver: BoundSolver | None):
    rests = Rests.from_table(inputs["rests"])
    turns = Turns.from_tables(inputs["turns"], inputs["gyro"], rests.t0_ns)
    acc = need_triad(inputs, "accel", "accel", "validate_turns")
    gyr = need_triad(inputs, "gyro_cal", "gyro", "validate_turns")
    _, E0, eps0, _, grav0 = turn_errors(rests, turns, None, None)
    Y1, E1, eps1, tilt, grav1 = turn_errors(rests, turns, acc, gyr)
    angle = np.degrees(2 * np.arctan(np.linalg.norm(Y1, axis=1)))
    informative = (np.degrees(tilt) >= params.min_tilt_deg) & (angle <= params.max_turn_deg)
    eps0_deg = np.where(informative, np.degrees(eps0), np.nan)
    eps1_deg = np.where(informative, np.degrees(eps1), np.nan)
    accepted = informative & (np.abs(np.nan_to_num(eps1_deg, nan=np.inf)) < params.tolerance_deg)
    n_inf = int(informative.sum())

    def rms(v):
        return float(np.sqrt(np.nanmean(v[informative] ** 2))) if n_inf else float("nan")

    summary = {
        "n_turns": len(turns), "n_informative": n_inf, "n_accepted": int(accepted.sum()),
        "tolerance_deg": params.tolerance_deg,
        "angle_error_rms_before_deg": rms(eps0_deg), "angle_error_rms_after_deg": rms(eps1_deg),
        "angle_error_max_after_deg": float(np.nanmax(np.abs(eps1_deg))) if n_inf else float("nan"),
        "gravity_error_rms_before_deg": float(np.degrees(np.sqrt(np.mean(grav0**2)))) if len(turns)
        else float("nan"),
        "gravity_error_rms_after_deg": float(np.degrees(np.sqrt(np.mean(grav1**2)))) if len(turns)
        else float("nan"),
        "passed": bool(n_inf and accepted.sum() == n_inf), "in_sample": True,
    }
    table = pa.table({
        "index": np.arange(len(turns), dtype=np.int64), "rest_before": turns.before,
        "rest_after": turns.after,
        "t_s": np.array([0.5 * (t[0] + t[-1]) if len(t) else np.nan for t in turns.t]),
        "angle_deg": angle, "tilt_deg": np.degrees(tilt),
        "rodrigues_error_before": E0, "rodrigues_error_after": E1,
        "angle_error_before_deg": eps0_deg, "angle_error_after_deg": eps1_deg,
        "gravity_error_before_deg": np.degrees(grav0), "gravity_error_after_deg": np.degrees(grav1),
        "informative": informative, "accepted": accepted,
    })
    return {"report": schemas.stamp(table, "validation", {"imupipe.summary": json.dumps(summary)})}


STAGE = Stage(
    name="validate_turns", version="2", func=validate,
    inputs={"rests": "rests", "turns": "turns", "gyro": "gyro", "accel": "calibration",
            "gyro_cal": "calibration"},
    outputs={"report": "validation"}, params=ValidateParams,
    description="Rodrigues and turn-angle errors of every turn, before and after calibration",
)
COMPONENTS = [STAGE]

"""Stage ``refine_joint``: one joint fit of accelerometer and gyroscope from any start.

Takes the rests and turns of the segmentation, the session's raw gyro, and the
calibrations of either method (A or B) as the starting point; a ``joint``
solver (default ``joint_ml``) refines both triads at once. Outputs a
``calibration`` table with the refined accel and gyro rows (``details``: the
1-sigma uncertainties, the joint (30, 30) covariance, the fit's chi2/dof per
block and the noise model), and the residuals of the model at the optimum:
``residuals`` (per rest: accel mean vs the forward model at the fitted gravity
direction, gyro mean vs the bias) and ``turn_residuals`` (per turn: the gravity
mismatch after the calibrated gyro, whitened, with the gyro bias random walk the
fit estimated). See docs/method-b.md.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import schemas
from ..components import BoundSolver, Params, Stage
from ..errors import SchemaError
from ..models import Calibration, TriadCalibration, triads_to_table
from ..observations import Rests, Turns
from ..solvers.joint_ml import JointFit, JointObservations
from ..solvers.turn_model import turn_mismatch, turn_temperature
from ._calib_common import concat_residuals, model_T, noise_details, residual_table

STANDARD_GRAVITY = 9.80665


class RefineParams(Params):
    solver: str = "joint_ml"
    solver_params: dict = Field(default_factory=dict)
    g_m_s2: float = STANDARD_GRAVITY
    """Local gravity magnitude, m/s^2 (the same value the accelerometer stage used)."""


def start_triads(tables: list[pa.Table]) -> tuple[TriadCalibration, TriadCalibration]:
    """The accel and gyro starting calibrations from the wired tables (later rows win)."""
    cal = Calibration.from_tables(*tables)
    missing = [s for s in ("accel", "gyro") if s not in cal.triads]
    if missing:
        raise SchemaError(
            f"refine_joint: the wired calibrations hold no {' or '.join(missing)} row; wire the "
            "outputs of the accelerometer and gyroscope stages to accel_calibration / gyro_calibration"
        )
    return cal["accel"], cal["gyro"]


def refined_triads(fit: JointFit, start: Mapping[str, TriadCalibration], solver: str,
                   rests: Rests | None = None) -> list[TriadCalibration]:
    """Calibration rows from a joint fit; k is the fitted one, else the start's. With
    ``rests``, each row's ``details["noise"]`` records the white noise the fit assumed."""
    rows = []
    for sensor in ("accel", "gyro"):
        tf = fit.triads[sensor]
        extra = {"start_solver": start[sensor].solver, "joint": fit.details}
        if rests is not None:
            extra["noise"] = noise_details(rests, sensor)
            walk = fit.details.get("gyro_bias_walk")
            if sensor == "gyro" and walk is not None:  # the drift the fit modelled (joint_ml)
                extra["noise"]["bias_random_walk"] = walk["sigma_rw"]
                extra["noise"]["bias_random_walk_unit"] = "rad/s/sqrt(s), per axis"
        if sensor == "accel":
            extra["joint_covariance"] = np.asarray(fit.cov).tolist()
            extra["joint_covariance_order"] = ("M_accel row-major (9), b0_accel (3), M_gyro (9), "
                                               "b0_gyro (3), k_accel (3), k_gyro (3)")
        if sensor in fit.sigma_k:
            k, sigma_k = fit.k[sensor], fit.sigma_k[sensor]
        else:
            k, sigma_k = start[sensor].k, start[sensor].details.get("sigma_k")
        rows.append(tf.to_calibration(sensor, solver, k=np.asarray(k),
                                      sigma_k=None if sigma_k is None else np.asarray(sigma_k),
                                      extra=extra))
    return rows


def fit_summary(fit: JointFit) -> dict:
    """The fit statistics the residual tables carry as ``imupipe.summary`` (as JSON)."""
    d = fit.details
    return {"chi2": d.get("chi2"), "dof": d.get("dof"), "chi2_per_dof": d.get("chi2_per_dof"),
            "blocks": d.get("blocks", {})}


def rest_residuals(rests: Rests, accel: TriadCalibration, gyro: TriadCalibration, fit: JointFit,
                   g: float) -> pa.Table:
    """``residuals`` rows ``refine_joint``/accel|gyro/rest: each rest's mean against the model.

    Accel: ``predict(g u_i, T)`` with ``u_i`` the fitted gravity direction (nuisance) of
    the rest; gyro: the bias at the rest's temperature. ``normalised`` by the white noise
    of the mean per axis; accel ``norm_error_*``: |g| error of the raw and calibrated mean.
    """
    mid = 0.5 * (rests.t_start_s + rests.t_end_s)
    T = model_T(rests.temperature)

    def sigma(sensor: str) -> np.ndarray:
        return np.sqrt(np.diagonal(rests.cov_of_mean(sensor), axis1=1, axis2=2))

    y_a, y_g = rests.need("accel"), rests.need("gyro")
    x = accel.apply(y_a, T)
    nx = np.linalg.norm(x, axis=1)
    # a solver that reports no nuisance directions: the calibrated measured ones
    u = x / nx[:, None] if fit.rest_gravity is None else fit.rest_gravity
    res_a = residual_table("refine_joint", "accel", "rest", mid, rests.temperature, y_a,
                           accel.predict(g * u, T), sigma("accel"),
                           np.linalg.norm(y_a, axis=1) / g - 1, nx / g - 1)
    res_g = residual_table("refine_joint", "gyro", "rest", mid, rests.temperature, y_g,
                           gyro.bias(T), sigma("gyro"))
    table = concat_residuals([res_a, res_g])
    return schemas.stamp(table, "residuals", {"imupipe.summary": json.dumps(fit_summary(fit))})


def turn_residuals(rests: Rests, turns: Turns, accel: TriadCalibration, gyro: TriadCalibration,
                   fit: JointFit) -> pa.Table:
    """A ``turn_residuals`` table of every wired turn under the refined calibration."""
    walk = fit.details.get("gyro_bias_walk", {}).get("q")
    tm = turn_mismatch(rests, turns, accel, gyro, None if walk is None else np.asarray(walk))
    m = len(turns)
    used = np.ones(m, bool) if fit.turns_used is None else np.asarray(fit.turns_used, bool)
    chi2 = tm.chi2
    mismatch = np.arctan2(np.linalg.norm(np.cross(tm.predicted, tm.measured), axis=1),
                          np.sum(tm.predicted * tm.measured, axis=1))
    l3, l2 = pa.list_(pa.float64(), 3), pa.list_(pa.float64(), 2)
    rows = int(2 * used.sum())
    summary = fit_summary(fit)
    summary["turns"] = {"chi2": float(chi2[used].sum()), "rows": rows,
                        "chi2_per_row": float(chi2[used].sum() / rows) if rows else None}
    table = pa.table({
        "stage": ["refine_joint"] * m, "index": np.arange(m, dtype=np.int64),
        "rest_before": turns.before.astype(np.int64), "rest_after": turns.after.astype(np.int64),
        "t_start_s": np.array([t[0] if len(t) else np.nan for t in turns.t], dtype=float),
        "t_end_s": np.array([t[-1] if len(t) else np.nan for t in turns.t], dtype=float),
        "temperature": turn_temperature(rests, turns),
        "used": used, "angle_deg": np.degrees(tm.angle),
        "measured": pa.array(list(tm.measured), type=l3), "predicted": pa.array(list(tm.predicted), type=l3),
        "residual": pa.array(list(tm.residual), type=l3), "mismatch_deg": np.degrees(mismatch),
        "whitened": pa.array(list(tm.whitened), type=l2), "chi2": chi2,
        "sigma_gyro_deg": np.degrees(tm.sigma_gyro), "sigma_rests_deg": np.degrees(tm.sigma_rests),
    })
    return schemas.stamp(table, "turn_residuals", {"imupipe.summary": json.dumps(summary)})


def refine_joint(inputs: Mapping[str, pa.Table], params: RefineParams,
                 solver: BoundSolver | None) -> dict[str, pa.Table]:
    accel, gyro = start_triads([inputs["accel_calibration"], inputs["gyro_calibration"]])
    rests = Rests.from_table(inputs["rests"])
    turns = Turns.from_tables(inputs["turns"], inputs["gyro"], rests.t0_ns)
    obs = JointObservations(rests, turns, params.g_m_s2, accel, gyro)
    fit = solver.solve(obs)
    acc, gyr = refined_triads(fit, {"accel": accel, "gyro": gyro}, solver.solver.name, rests)
    return {"calibration": triads_to_table([acc, gyr]),
            "residuals": rest_residuals(rests, acc, gyr, fit, params.g_m_s2),
            "turn_residuals": turn_residuals(rests, turns, acc, gyr, fit)}


STAGE = Stage(
    name="refine_joint",
    version="3",
    func=refine_joint,
    inputs={"rests": "rests", "turns": "turns", "gyro": "gyro",
            "accel_calibration": "calibration", "gyro_calibration": "calibration"},
    outputs={"calibration": "calibration", "residuals": "residuals", "turn_residuals": "turn_residuals"},
    params=RefineParams,
    solver_kind="joint",
    description="Joint maximum-likelihood refinement of accelerometer and gyroscope over all rests "
                "and turns, started from any method's answer; returns covariances.",
)

COMPONENTS = [STAGE]

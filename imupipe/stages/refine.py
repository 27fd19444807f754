"""Stage ``refine_joint``: one joint fit of accelerometer and gyroscope from any start.

Takes the rests and turns of the segmentation, the session's raw gyro, and the
calibrations of either method (A or B) as the starting point; a ``joint``
solver (default ``joint_ml``) refines both triads at once. Outputs a
``calibration`` table with the refined accel and gyro rows; their ``details``
carry the 1-sigma uncertainties and the joint (24, 24) covariance.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from ..components import BoundSolver, Params, Stage
from ..errors import SchemaError
from ..models import Calibration, TriadCalibration, triads_to_table
from ..observations import Rests, Turns
from ..solvers.joint_ml import JointFit, JointObservations

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


def refined_triads(fit: JointFit, start: Mapping[str, TriadCalibration], solver: str) -> list[TriadCalibration]:
    """Calibration rows from a joint fit; k is the fitted one, else the start's."""
    rows = []
    for sensor in ("accel", "gyro"):
        tf = fit.triads[sensor]
        extra = {"start_solver": start[sensor].solver, "joint": fit.details}
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


def refine_joint(inputs: Mapping[str, pa.Table], params: RefineParams,
                 solver: BoundSolver | None) -> dict[str, pa.Table]:
    accel, gyro = start_triads([inputs["accel_calibration"], inputs["gyro_calibration"]])
    rests = Rests.from_table(inputs["rests"])
    turns = Turns.from_tables(inputs["turns"], inputs["gyro"], rests.t0_ns)
    obs = JointObservations(rests, turns, params.g_m_s2, accel, gyro)
    fit = solver.solve(obs)
    rows = refined_triads(fit, {"accel": accel, "gyro": gyro}, solver.solver.name)
    return {"calibration": triads_to_table(rows)}


STAGE = Stage(
    name="refine_joint",
    version="1",
    func=refine_joint,
    inputs={"rests": "rests", "turns": "turns", "gyro": "gyro",
            "accel_calibration": "calibration", "gyro_calibration": "calibration"},
    outputs={"calibration": "calibration"},
    params=RefineParams,
    solver_kind="joint",
    description="Joint maximum-likelihood refinement of accelerometer and gyroscope over all rests "
                "and turns, started from any method's answer; returns covariances.",
)

COMPONENTS = [STAGE]

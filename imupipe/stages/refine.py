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
from ..components import BoundSolver, LocalGravity, Params, Stage
from ..errors import SchemaError
from ..models import Calibration, TriadCalibration, triads_to_table
from ..observations import Rests, Turns
from ..solvers.joint_ml import JointFit, JointObservations
from ..rotations import rotation_angle
from ..temperature import smoothed
from ._calib_common import concat_residuals, noise_details, residual_table

STANDARD_GRAVITY = 9.80665


class RefineParams(Params):
    solver: str = "joint_ml"
    solver_params: dict = Field(default_factory=dict)
    g_m_s2: LocalGravity = STANDARD_GRAVITY
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
            walk = fit.details.get(f"{sensor}_bias_walk")
            if walk is not None:  # the drift the fit modelled (joint_ml)
                extra["noise"]["bias_random_walk"] = walk["sigma_rw"]
                extra["noise"]["bias_random_walk_unit"] = walk["sigma_rw_unit"] + ", per axis"
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


def rest_residuals(rests: Rests, fit: JointFit) -> pa.Table:
    """``residuals`` rows ``refine_joint``/accel|gyro/rest: each rest's mean against the fitted
    forward model (the gravity direction fitted as a nuisance, the bias walks' averages over
    the rest). ``normalised``: the fit's whitened residual of the rest (whitened by its own
    covariance and the walks' averaging variance, lower-triangular Cholesky: x, then y given x,
    then z given x and y); accel ``norm_error_*``: |g| error of the raw and calibrated mean."""
    lin = fit.linearised
    model = lin.model
    _, _, _, sig = model.residuals(lin.x_g, lin.x_l, signals=True, jacobian=False)
    mid = 0.5 * (rests.t_start_s + rests.t_end_s)
    tables = []
    for sensor, block, pred in (("accel", "accel_rest", sig["pred_accel_rest"]),
                                ("gyro", "gyro_rest", sig["pred_gyro_rest"])):
        y = rests.need(sensor)
        z = lin.r[lin.rows.of(block)].reshape(-1, 3)
        extra = ()
        if sensor == "accel":
            P = model.unpack(lin.x_g)
            x = (y - pred + sig["gravity_rest"] * model.g @ P["S_a"].T) @ np.linalg.inv(P["S_a"]).T
            extra = (np.linalg.norm(y, axis=1) / model.g - 1, np.linalg.norm(x, axis=1) / model.g - 1)
        t = residual_table("refine_joint", sensor, "rest", mid, rests.temperature, y, pred, None, *extra)
        tables.append(t.set_column(t.schema.get_field_index("normalised"), "normalised",
                                   pa.array(list(z), type=pa.list_(pa.float64(), 3))))
    table = concat_residuals(tables)
    return schemas.stamp(table, "residuals", {"imupipe.summary": json.dumps(fit_summary(fit))})


def turn_residuals(rests: Rests, turns: Turns, fit: JointFit) -> pa.Table:
    """A ``turn_residuals`` table of every wired turn under the refined calibration: the fit's
    whitened turn rows (the gravity carried through the turn against the gravity fitted after
    it); turns the fit left out (saturated) carry NaN."""
    lin = fit.linearised
    model = lin.model
    m = len(turns)
    used = np.ones(m, bool) if fit.turns_used is None else np.asarray(fit.turns_used, bool)
    view = model.turn_view(lin.x_g, lin.x_l)
    Q = fit.frame if fit.frame is not None else np.eye(3)

    def spread(values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        out = np.full((m,) + values.shape[1:], fill)
        out[used] = values
        return out

    w = lin.r[lin.rows.of("turn")].reshape(-1, 2)
    pred, meas = spread(view["predicted"] @ Q), spread(view["measured"] @ Q)
    chi2 = np.sum(spread(w) ** 2, axis=1)
    P = model.unpack(lin.x_g)
    sigma_rests = np.full(m, np.nan)
    if used.any():
        u = model.gravity(lin.x_l)[0]
        cov_u = _direction_cov(rests, u, P, model.g)
        R = view["rotation"]
        p, q = model.p, model.qr
        c = np.swapaxes(R, 1, 2) @ cov_u[p] @ R + cov_u[q]
        sigma_rests[used] = np.sqrt(np.trace(c, axis1=1, axis2=2) / 2)
    mismatch = np.arctan2(np.linalg.norm(np.cross(pred, meas), axis=1), np.sum(pred * meas, axis=1))
    angle = spread(np.degrees(rotation_angle(view["rotation"])))
    l3, l2 = pa.list_(pa.float64(), 3), pa.list_(pa.float64(), 2)
    rows = int(2 * used.sum())
    summary = fit_summary(fit)
    summary["turns"] = {"chi2": float(np.nansum(chi2)), "rows": rows,
                        "chi2_per_row": float(np.nansum(chi2) / rows) if rows else None}
    t_mid = np.array([0.5 * (t[0] + t[-1]) if len(t) else np.nan for t in turns.t])
    table = pa.table({
        "stage": ["refine_joint"] * m, "index": np.arange(m, dtype=np.int64),
        "rest_before": turns.before.astype(np.int64), "rest_after": turns.after.astype(np.int64),
        "t_start_s": np.array([t[0] if len(t) else np.nan for t in turns.t], dtype=float),
        "t_end_s": np.array([t[-1] if len(t) else np.nan for t in turns.t], dtype=float),
        "temperature": model.temperature_at(np.nan_to_num(t_mid)),
        "used": used, "angle_deg": angle,
        "measured": pa.array(list(meas), type=l3), "predicted": pa.array(list(pred), type=l3),
        "residual": pa.array(list(meas - pred), type=l3), "mismatch_deg": np.degrees(mismatch),
        "whitened": pa.array(list(spread(w)), type=l2), "chi2": chi2,
        "sigma_gyro_deg": np.degrees(spread(view["sigma_gyro"])), "sigma_rests_deg": np.degrees(sigma_rests),
    })
    return schemas.stamp(table, "turn_residuals", {"imupipe.summary": json.dumps(summary)})


def _direction_cov(rests: Rests, u: np.ndarray, P: dict, g: float) -> np.ndarray:
    """(n, 3, 3) covariance of each rest's gravity direction from its accel mean's white noise
    (first order: ``(I - u u^T) S^-1 / g``), gauge frame."""
    A = (np.eye(3) - np.einsum("ni,nj->nij", u, u)) @ np.linalg.inv(P["S_a"]) / g
    return A @ rests.cov_of_mean("accel") @ np.swapaxes(A, 1, 2)


def temperature_stream(table: pa.Table | None, t0_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``(t s since t0_ns, T degC de-quantised)`` of a ``temperature`` table, or None."""
    if table is None or not table.num_rows:
        return None
    t = (table.column("t_ns").to_numpy() - t0_ns) * 1e-9
    return t, smoothed(t, table.column("temperature").to_numpy().astype(float))


def refine_joint(inputs: Mapping[str, pa.Table], params: RefineParams,
                 solver: BoundSolver | None) -> dict[str, pa.Table]:
    accel, gyro = start_triads([inputs["accel_calibration"], inputs["gyro_calibration"]])
    rests = Rests.from_table(inputs["rests"])
    turns = Turns.from_tables(inputs["turns"], inputs["gyro"], rests.t0_ns)
    obs = JointObservations(rests, turns, params.g_m_s2, accel, gyro,
                            temperature_stream(inputs.get("temperature"), rests.t0_ns))
    fit = solver.solve(obs)
    acc, gyr = refined_triads(fit, {"accel": accel, "gyro": gyro}, solver.solver.name, rests)
    return {"calibration": triads_to_table([acc, gyr]),
            "residuals": rest_residuals(rests, fit),
            "turn_residuals": turn_residuals(rests, turns, fit)}


STAGE = Stage(
    name="refine_joint",
    version="5",
    func=refine_joint,
    inputs={"rests": "rests", "turns": "turns", "gyro": "gyro",
            "accel_calibration": "calibration", "gyro_calibration": "calibration",
            "temperature": "temperature"},
    optional_inputs=frozenset({"temperature"}),
    outputs={"calibration": "calibration", "residuals": "residuals", "turn_residuals": "turn_residuals"},
    params=RefineParams,
    solver_kind="joint",
    description="Joint maximum-likelihood refinement of accelerometer and gyroscope over all rests "
                "and turns, started from any method's answer; returns covariances.",
)

COMPONENTS = [STAGE]

"""Stage ``map_residuals``: predict every sample under the calibration and map where it fails.

Inputs: the session's raw ``accel`` and ``gyro`` (and ``temperature``), the
segmentation's ``rests`` and ``turns`` (and the ``events`` of ``screen_events``:
gaps, shocks, splices), and the ``calibration`` to judge (the joint refinement's, whose
details carry the noise model it fitted: the bias walks); optionally the raw ``mag`` and its
``mag_calibration``, judged at the rests and in the motions (``diagnosis.magnetic``). Outputs the per-sample
residual table (``sample_residuals``) and the residual map (``residual_map``: its
cells as rows, the whole ``residual_map.json`` document in the schema metadata).
See ``imupipe.diagnosis`` and docs/residual-map.md.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import schemas
from ..components import BoundSolver, LocalGravity, Params, Stage
from ..models import Calibration
from ..observations import Rests, Turns
from .refine import STANDARD_GRAVITY, temperature_stream
from .segment import xyz

# the diagnosis (SciPy's stats, ruptures) is imported when a stage runs, not when it is registered
if TYPE_CHECKING:
    from ..diagnosis.evaluate import Evaluation, Event

MAP_KEY = b"imupipe.residual_map"
DIAGNOSIS_KEY = b"imupipe.diagnosis"


class MapParams(Params):
    knot_s: float = Field(0.25, gt=0)
    """Spacing of the attitude-error knots inside each motion, s."""
    fdr_q: float = Field(0.05, gt=0, lt=1)
    """False-discovery rate of the flagged cells (Benjamini-Hochberg)."""
    g_m_s2: LocalGravity | None = None
    """Local gravity, m/s^2; default: the one the calibration was fitted with."""
    latitude_deg: float | None = Field(None, ge=-90, le=90)
    """The recording's latitude, deg, when known: the diagnosis then names a vertical gyro rate
    within 3 sd of Earth's there Earth's rate (without it, an ``unknown`` naming Earth's rate and
    an isotropic g-sensitivity: at rest the two are the same)."""


def _events(table: pa.Table | None) -> list[Event]:
    from ..diagnosis.events import Event

    if table is None:
        return []
    cols = set(table.column_names)
    out = []
    for row in table.to_pylist():
        out.append(Event(str(row.get("kind", "event")), str(row.get("sensor", "")),
                         (float(row["t_start_s"]), float(row["t_end_s"])),
                         str(row.get("detail", "")) if "detail" in cols else ""))
    return out


def null_walks(cal: Calibration, rests: Rests, gravity: float) -> tuple[np.ndarray, np.ndarray]:
    """(3,) and (3,): the accelerometer's and the gyro's bias random-walk intensities of the
    diagnosis's null model: the joint refinement's (zeros without one), with a walk it estimated
    but did not detect (zero at its 5 % test) estimated at the likelihood's maximum under the
    fitted calibration instead. Set to zero, a weak walk's wander passes for slow misfit
    (measured: on a standard null, an accelerometer walk of 1e-10 (m/s^2)^2/s, not detected,
    made an accelerometer term significant; estimated 5.8e-11, none)."""
    from ..solvers.joint_ml import accel_walk_intensity, gyro_walk_intensity

    joint = cal["gyro"].details.get("joint", {})
    q_a, q_g = (np.asarray(joint.get(f"{s}_bias_walk", {}).get("q", [0.0] * 3), float) for s in ("accel", "gyro"))
    fit_k = bool(joint.get("fitted_temperature_coefficients"))
    if joint.get("gyro_bias_walk", {}).get("estimated") and not q_g.any():
        q_g = gyro_walk_intensity(rests, cal["gyro"], fit_k, None, min_lr=0.0)[0]
    if joint.get("accel_bias_walk", {}).get("estimated") and not q_a.any():
        q_a = accel_walk_intensity(rests, cal["accel"], gravity, fit_k, None, min_lr=0.0)
    return q_a, q_g


def evaluation(inputs: Mapping[str, pa.Table], params: MapParams,
               walks: tuple[np.ndarray, np.ndarray] | None = None) -> Evaluation:
    """The per-sample model of the session under the input calibration (held fixed); ``walks``:
    the bias walks' intensities ``(q_a, q_g)`` instead of ``null_walks`` (a pooled estimate)."""
    from ..diagnosis.evaluate import evaluate

    rests = Rests.from_table(inputs["rests"])
    turns = Turns.from_tables(inputs["turns"], inputs["gyro"], rests.t0_ns)
    cal = Calibration.from_tables(inputs["calibration"])
    accel, gyro = cal["accel"], cal["gyro"]
    joint = gyro.details.get("joint", {})
    g = params.g_m_s2 or float(joint.get("gravity_m_s2", STANDARD_GRAVITY))
    q_a, q_g = walks if walks is not None else null_walks(cal, rests, g)
    streams = {}
    for s in ("accel", "gyro"):
        t_ns, y = xyz(inputs[s])
        streams[s] = ((t_ns - rests.t0_ns) * 1e-9, y)
    return evaluate(streams, rests, turns, accel, gyro, g, q_a, q_g,
                    temperature_stream(inputs.get("temperature"), rests.t0_ns),
                    _events(inputs.get("events")), knot_s=params.knot_s)


def magnetometer_rows(inputs: Mapping[str, pa.Table], ev: Evaluation) -> tuple:
    """The magnetometer's rest, within-rest and motion rows for the map (``diagnosis.magnetic``),
    when the session has one and its calibration is wired in (``mag_calibration``)."""
    from ..diagnosis.evaluate import effective_counts
    from ..diagnosis.magnetic import motion_rows, rest_rows, scatter_rows

    if inputs.get("mag") is None or inputs.get("mag_calibration") is None:
        return ()
    mag_cal = Calibration.from_tables(inputs["mag_calibration"])
    cal = Calibration.from_tables(inputs["calibration"])
    if "mag" not in mag_cal.triads or "accel" not in cal.triads:
        return ()
    rests = Rests.from_table(inputs["rests"])
    if not rests.has("mag"):
        return ()
    t_ns, y = xyz(inputs["mag"])
    t = (t_ns - rests.t0_ns) * 1e-9
    rests = effective_counts(rests, {"mag": (t, y)})
    temperature = temperature_stream(inputs.get("temperature"), rests.t0_ns)
    at_rests, refit = rest_rows(rests, cal["accel"], mag_cal["mag"]) or (None, None)
    rows = (at_rests, scatter_rows(rests, t, y, mag_cal["mag"].k, temperature),
            motion_rows(ev, rests, t, y, refit, temperature) if refit is not None else None)
    return tuple(rs for rs in rows if rs is not None)


def map_residuals(inputs: Mapping[str, pa.Table], params: MapParams, solver: BoundSolver | None) -> dict:
    from ..diagnosis.residual_map import residual_map

    ev = evaluation(inputs, params)
    doc = residual_map(ev, q=params.fdr_q, extra=lambda: magnetometer_rows(inputs, ev), keep_jacobians=False)
    meta = {MAP_KEY.decode(): json.dumps(doc)}
    return {"samples": ev.samples, "map": schemas.stamp(_cell_table(doc["cells"]), "residual_map", meta)}


def _cell_table(cells: list[dict]) -> pa.Table:
    return pa.table({
        "rank": np.array([c["rank"] for c in cells], dtype=np.int64),
        "sensor": [c["sensor"] for c in cells], "axes": [",".join(c["axes"]) for c in cells],
        "regime": [c["regime"] for c in cells], "variable": [c["variable"] for c in cells],
        "lo": [_edge(c["range"][0]) for c in cells], "hi": [_edge(c["range"][1]) for c in cells],
        "chi2": [c["chi2"] for c in cells], "dof": [c["dof"] for c in cells],
        "chi2_per_dof": [c["chi2_per_dof"] for c in cells], "p_value": [c["p_value"] for c in cells],
        "flagged": [c["flagged"] for c in cells],
    })


def _edge(x) -> float:
    if isinstance(x, str) or x is None:
        return float("nan")
    return float(x)


STAGE = Stage(
    name="map_residuals",
    version="16",
    func=map_residuals,
    inputs={"accel": "accel", "gyro": "gyro", "temperature": "temperature", "rests": "rests",
            "turns": "turns", "calibration": "calibration", "events": "events", "mag": "mag",
            "mag_calibration": "calibration"},
    outputs={"samples": "sample_residuals", "map": "residual_map"},
    params=MapParams,
    optional_inputs=frozenset({"temperature", "events", "mag", "mag_calibration"}),
    description="Every sample predicted under the calibration (rests, turns, motions), whitened "
                "by the recording's noise model; chi2/dof per sensor x axis x regime cell with "
                "Benjamini-Hochberg flags, change points and events.",
)



def diagnose_session(inputs: Mapping[str, pa.Table], params: MapParams, solver: BoundSolver | None) -> dict:
    from ..diagnosis.diagnose import diagnose
    from ..diagnosis.residual_map import residual_map
    from ..plugins import make_registry

    ev = evaluation(inputs, params)
    doc = residual_map(ev, q=params.fdr_q, extra=lambda: magnetometer_rows(inputs, ev))
    registry = make_registry()
    effects = {name: registry.get("effects", name) for name in registry.names("effects")}
    diag = diagnose(ev, doc, effects, q=params.fdr_q, latitude_deg=params.latitude_deg)
    table = pa.table({
        "effect": [f["effect"] for f in diag["findings"]],
        "sensor": [f["sensor"] for f in diag["findings"]],
        "regime": [f["regime"] for f in diag["findings"]],
        "p_value": pa.array([f["significance"]["p_value"] for f in diag["findings"]], pa.float64()),
    })
    return {"samples": ev.samples,
            "diagnosis": schemas.stamp(table, "diagnosis", {DIAGNOSIS_KEY.decode(): json.dumps(diag)}),
            "map": schemas.stamp(_cell_table(doc["cells"]), "residual_map", {MAP_KEY.decode(): json.dumps(doc)})}


DIAGNOSE = Stage(
    name="diagnose",
    version="21",
    func=diagnose_session,
    inputs=STAGE.inputs,
    outputs={"samples": "sample_residuals", "map": "residual_map", "diagnosis": "diagnosis"},
    params=MapParams,
    optional_inputs=frozenset({"temperature", "events", "mag", "mag_calibration"}),
    description="The residual map, then every catalogue effect tested against the fitted per-sample "
                "model (score tests, Benjamini-Hochberg forward selection, held-out check): "
                "diagnosis.json.",
)

COMPONENTS = [STAGE, DIAGNOSE]

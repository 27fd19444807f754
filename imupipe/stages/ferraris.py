"""Ferraris / six-pose + known-angle turns (imucal's protocol) from named sections.

The six static poses (``x_p``: +x up, ``x_a``: -x up, ... ``z_a``) and three turns
(``x_rot``, ``y_rot``, ``z_rot``: one known angle, typically a full turn, about the
vertical axis while that axis is up) come from the session manifest's section list
(``session.sections``, imucal's names). Without one, they are found from the stillness
segmentation (``rests``, ``turns``): each rest is named by the axis nearest gravity,
a pose takes every rest of its name, and each turn is the motion between two rests of
the same axis that integrates to the most about that axis (imupipe's own ``simulate
ferraris`` records this way).

Before fitting, each pose is checked to have gravity along its axis (a mislabelled
section list is refused naming the section) and to be at rest (gyro scatter against the
other poses'), and each turn to hold no stamp gap.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from ..components import BoundSolver, LocalGravity, Params, Stage
from ..errors import SolverError
from ..models import triads_to_table
from ..observations import Rests
from ..solvers.ferraris import POSES, TURNS, FerrarisObservations
from ._calib_common import residual_table
from .segment import xyz


class FerrarisStageParams(Params):
    """``g_m_s2``: local gravity (imucal's example uses 9.81); ``turn_angle_deg``: the turns'
    known angle, signed about the up axis (imucal: -360, clockwise); None: a full turn in the
    direction the gyro saw. ``max_pose_tilt_deg``: how far a pose's gravity may be from its
    axis before the section is refused; ``max_pose_motion``: how many times the poses' median
    gyro scatter one pose may show before it is refused as moving; ``max_gap_s``: a stamp gap inside a turn that refuses it."""

    g_m_s2: LocalGravity = 9.80665
    turn_angle_deg: float | None = Field(None, ge=-3600, le=3600)
    max_pose_tilt_deg: float = Field(20.0, gt=0, le=90)
    max_pose_motion: float = Field(10.0, gt=1)
    max_gap_s: float = Field(0.1, gt=0)
    solver: str = "ferraris"
    solver_params: dict = Field(default_factory=dict)


def _select(t: np.ndarray, v: np.ndarray, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    i0, i1 = np.searchsorted(t, a, "left"), np.searchsorted(t, b, "right")
    return t[i0:i1], v[i0:i1]


def sections_from_table(table: pa.Table) -> dict[str, tuple[int, int]]:
    names = table.column("name").to_pylist()
    return dict(zip(names, zip(table.column("t_start_ns").to_pylist(),
                               table.column("t_end_ns").to_pylist(), strict=True), strict=True))


def sections_from_segments(rests: Rests, turns: pa.Table, tg: np.ndarray, wg: np.ndarray
                           ) -> dict[str, list[tuple[int, int]]]:
    """Pose and turn windows (ns) from the segmentation, named as imucal names them."""
    acc = rests.need("accel")
    axis = np.argmax(np.abs(acc), axis=1)
    names = [f"{'xyz'[i]}_{'p' if acc[k, i] > 0 else 'a'}" for k, i in enumerate(axis)]
    t0 = rests.t0_ns
    out: dict[str, list[tuple[int, int]]] = {}
    for k, name in enumerate(names):
        out.setdefault(name, []).append((t0 + round(rests.t_start_s[k] * 1e9),
                                         t0 + round(rests.t_end_s[k] * 1e9)))
    bias = np.mean(rests.need("gyro"), axis=0)
    best: dict[str, tuple[float, tuple[int, int]]] = {}
    for before, after, a, b in zip(turns.column("rest_before").to_pylist(),
                                   turns.column("rest_after").to_pylist(),
                                   turns.column("t_start_ns").to_pylist(),
                                   turns.column("t_end_ns").to_pylist(), strict=True):
        if axis[before] != axis[after]:
            continue
        i = int(axis[before])
        t, w = _select(tg, wg, a, b)
        if len(t) < 2:
            continue
        turned = abs(float(np.sum((w[:, i] - bias[i]) * np.gradient(t * 1e-9))))
        if turned > np.radians(180) and turned > best.get("xyz"[i], (0.0, None))[0]:
            best["xyz"[i]] = (turned, (a, b))
    for a, (_, window) in best.items():
        out[f"{a}_rot"] = [window]
    return out


def calibrate_ferraris(inputs: Mapping[str, pa.Table], params: FerrarisStageParams,
                       solver: BoundSolver | None):
    ta, va = xyz(inputs["accel"])
    tg, vg = xyz(inputs["gyro"])
    if "sections" in inputs:
        windows = {k: [v] for k, v in sections_from_table(inputs["sections"]).items()}
        source = "section list"
        fix = "add them to the manifest's [sections] (imucal's names)"
    elif "rests" in inputs and "turns" in inputs:
        rests = Rests.from_table(inputs["rests"])
        windows = sections_from_segments(rests, inputs["turns"], tg, vg)
        source = "stillness segmentation"
        fix = ("record each axis up and down at rest, and a full turn about each axis while it "
               "is up, or give the manifest a [sections] list")
    else:
        raise SolverError("calibrate_ferraris: needs the session's section list (wire "
                          "session.sections) or the segmentation's rests and turns")
    missing = [n for n in (*POSES, *TURNS) if n not in windows]
    if missing:
        raise SolverError(f"calibrate_ferraris: the {source} lacks {', '.join(missing)} "
                          f"(found: {', '.join(sorted(windows)) or 'none'}); {fix}")

    def gather(t, v, name):
        parts = [_select(t, v, a, b) for a, b in windows[name]]
        return np.concatenate([p[0] for p in parts]), np.vstack([p[1] for p in parts])

    g = params.g_m_s2
    pose_acc, pose_gyr = {}, {}
    for p in POSES:
        pose_acc[p], pose_gyr[p] = gather(ta, va, p)[1], gather(tg, vg, p)[1]
        if len(pose_acc[p]) < 2 or len(pose_gyr[p]) < 2:
            raise SolverError(f"calibrate_ferraris: pose {p!r} holds {len(pose_acc[p])} accel and "
                              f"{len(pose_gyr[p])} gyro samples; it needs a few seconds at rest")
        m = pose_acc[p].mean(axis=0)
        i, sign = "xyz".index(p[0]), 1 if p[2] == "p" else -1
        tilt = np.degrees(np.arccos(np.clip(sign * m[i] / np.linalg.norm(m), -1, 1)))
        if tilt > params.max_pose_tilt_deg:
            raise SolverError(
                f"calibrate_ferraris: pose {p!r} ({source}) has gravity {tilt:.0f} deg from "
                f"{'+' if sign > 0 else '-'}{p[0]} (mean accel {np.round(m, 2).tolist()} m/s^2): "
                "the section list or the pose is mislabelled; fix the section")
    scatter = {p: float(np.linalg.norm(pose_gyr[p].std(axis=0))) for p in POSES}
    floor = float(np.median(list(scatter.values())))
    for p in POSES:
        if scatter[p] > params.max_pose_motion * max(floor, 1e-12):
            raise SolverError(
                f"calibrate_ferraris: pose {p!r} ({source}) is not at rest: its gyro scatter is "
                f"{scatter[p] / floor:.0f}x the poses' median (a turn inside the section?); fix "
                f"the section, or raise max_pose_motion = {params.max_pose_motion}")
    turn_acc, turn_gyr, turn_dt = {}, {}, {}
    for name in TURNS:
        t, w = gather(tg, vg, name)
        if len(t) < 3:
            raise SolverError(f"calibrate_ferraris: turn {name!r} holds {len(t)} gyro samples")
        dt = np.diff(t) * 1e-9
        if dt.max() > params.max_gap_s:
            k = int(np.argmax(dt))
            raise SolverError(
                f"calibrate_ferraris: turn {name!r} has a {dt[k]:.3f} s gap in the gyro stamps "
                f"at {(t[k] - ta[0]) * 1e-9:.2f} s; the angle cannot be integrated across it "
                f"(raise max_gap_s = {params.max_gap_s} only if the gap is known to be still)")
        turn_dt[name] = np.r_[dt, np.median(dt)]  # each sample holds until the next
        turn_gyr[name] = w
        # the accelerometer at the gyro's stamps (the g-sensitivity term of the turn)
        turn_acc[name] = np.column_stack([np.interp(t, ta, va[:, j]) for j in range(3)])
    angle = np.radians(params.turn_angle_deg) if params.turn_angle_deg is not None else None
    fits = solver.solve(FerrarisObservations(pose_acc, pose_gyr, turn_acc, turn_gyr, turn_dt, g,
                                             angle))
    extra = {"sections_source": source}
    cal_a = fits["accel"].to_calibration("accel", solver.solver.name, extra=extra)
    cal_g = fits["gyro"].to_calibration("gyro", solver.solver.name, extra=extra)

    y = np.array([pose_acc[p].mean(axis=0) for p in POSES])
    x = cal_a.apply(y)
    nx = np.linalg.norm(x, axis=1)
    predicted = cal_a.predict(x / nx[:, None] * g)
    sigma = np.array([pose_acc[p].std(axis=0) / np.sqrt(len(pose_acc[p])) for p in POSES])
    mid = np.array([(np.mean([a for a, _ in windows[p]]) - ta[0]) * 1e-9 for p in POSES])
    res = residual_table("calibrate_ferraris", "accel", "rest", mid, np.full(6, np.nan), y,
                         predicted, np.where(sigma > 0, sigma, np.nan),
                         np.linalg.norm(y, axis=1) / g - 1, nx / g - 1)
    return {"calibration": triads_to_table([cal_a, cal_g]), "residuals": res}


STAGE = Stage(
    name="calibrate_ferraris", version="1", func=calibrate_ferraris,
    inputs={"accel": "accel", "gyro": "gyro", "sections": "sections", "rests": "rests",
            "turns": "turns"},
    outputs={"calibration": "calibration", "residuals": "residuals"},
    params=FerrarisStageParams, optional_inputs=frozenset({"sections", "rests", "turns"}),
    solver_kind="ferraris",
    description="accelerometer and gyroscope from six poses and three known-angle turns "
                "(Ferraris; imucal's protocol), by the session's section list",
)
COMPONENTS = [STAGE]

"""Method A stages end to end on a simulated standard session: recovery against the truth."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pytest

from imupipe import schemas
from imupipe.components import BoundSolver
from imupipe.diagnosis.attitude import MotionSamples
from imupipe.errors import SolverError
from imupipe.models import triads_from_table
from imupipe.observations import Rests, Turns
from imupipe.sim.api import simulate_recording
from imupipe.solvers.ellipsoid_cholesky import EllipsoidCholesky, EllipsoidParams
from imupipe.solvers.gyro_rodrigues import GyroRodrigues, GyroRodriguesParams
from imupipe.solvers.mag_dip import MagDip, MagDipParams
from imupipe.solvers.thermal_kalman import ThermalKalman, ThermalKalmanParams
from imupipe.solvers.thermal_poly import ThermalPoly, ThermalPolyParams
from imupipe.stages import accel, gyro, mag, segment, thermal, validate

ACC_BIAS_TOL_MG = 0.2
ACC_M_TOL_PPM = 200
MAG_M_TOL = 0.002  # 0.2 %
GYRO_M_TOL_PPM = 1500  # noise-limited: 150 turns of <= 5 deg (see docs/method-a.md)
GYRO_BIAS_TOL_DPS = 0.005
K_TOL_SIGMA = 5.0
Z_MAX = 5.0  # reported 1-sigma: 6-seed RMS z-scores are 0.5-1.6 (docs/method-a.md)


@pytest.fixture(scope="module")
def session():
    rec, truth = simulate_recording("standard", None, 11, n_positions=120, warmup_s=300)
    d = dict(rec.device("imu"))
    seg = segment.STAGE.func(d, segment.SegmentParams(), None)
    th = thermal.STAGE.func({**d, "rests": seg["rests"]}, thermal.ThermalParams(),
                            BoundSolver(ThermalKalman(), ThermalKalmanParams()))
    env = truth.data["environment"]
    ref, true_rests = truth.reference_rests, truth.rests
    acc_params = accel.AccelParams(g_m_s2=env["g_m_s2"],
                                   y_up_time_s=true_rests[ref["reference_y_up"]].mean(),
                                   x_up_time_s=true_rests[ref["reference_x_up"]].mean())
    ac = accel.STAGE.func({"rests": seg["rests"], "thermal": th["calibration"]}, acc_params,
                          BoundSolver(EllipsoidCholesky(), EllipsoidParams()))
    mg = mag.STAGE.func({"rests": seg["rests"], "accel": ac["calibration"], "mag": d["mag"],
                         "thermal": th["calibration"]}, mag.MagParams(field_T=env["field_T"]),
                        BoundSolver(MagDip(), MagDipParams()))
    gy = gyro.STAGE.func({"rests": seg["rests"], "turns": seg["turns"], "gyro": d["gyro"],
                          "accel": ac["calibration"], "thermal": th["calibration"]},
                         gyro.GyroParams(), BoundSolver(GyroRodrigues(), GyroRodriguesParams()))
    va = validate.STAGE.func({"rests": seg["rests"], "turns": seg["turns"], "gyro": d["gyro"],
                              "accel": ac["calibration"], "gyro_cal": gy["calibration"]},
                             validate.ValidateParams(), None)
    return {"d": d, "truth": truth, "seg": seg, "th": th, "ac": ac, "mg": mg, "gy": gy, "va": va}


def one(table: pa.Table, sensor: str):
    return next(t for t in triads_from_table(table) if t.sensor == sensor)


def assert_within_sigma(cal, true, n_sigma: float = Z_MAX) -> None:
    """Errors of M and b0 stay within n_sigma of the uncertainty the stage reports."""
    sd_M, sd_b = np.array(cal.details["sigma_M"]), np.array(cal.details["sigma_b0"])
    assert np.all(np.abs(cal.M - true.M) <= n_sigma * sd_M + 1e-12)
    assert np.all(np.abs(cal.b0 - true.b0) <= n_sigma * sd_b)


def test_outputs_follow_their_schemas(session):
    for key, port, sid in [("seg", "rests", "rests"), ("seg", "turns", "turns"),
                           ("th", "residuals", "residuals"), ("ac", "calibration", "calibration"),
                           ("ac", "residuals", "residuals"), ("mg", "residuals", "residuals"),
                           ("gy", "residuals", "residuals"), ("va", "report", "validation")]:
        schemas.check(session[key][port], sid)


def test_segmentation_finds_the_true_rests(session):
    rests = Rests.from_table(session["seg"]["rests"])
    true = session["truth"].rests
    assert abs(len(rests) - len(true)) <= 3
    mid = 0.5 * (rests.t_start_s + rests.t_end_s)
    inside = [(np.any((true[:, 0] - 0.05 <= a) & (true[:, 1] + 0.05 >= b)))
              for a, b in zip(rests.t_start_s, rests.t_end_s, strict=True)]
    assert np.mean(inside) > 0.97  # detected rests lie within true rests
    assert np.all(np.diff(mid) > 0)
    assert session["seg"]["turns"].num_rows == len(rests) - 1


def test_segmentation_tolerates_irregular_stamps(session):
    rng = np.random.default_rng(0)
    d = {}
    for s in ("accel", "gyro"):
        t = session["d"][s]
        keep = np.sort(rng.choice(t.num_rows, int(0.7 * t.num_rows), replace=False))  # bursty loss
        d[s] = t.take(pa.array(keep))
    out = segment.STAGE.func(d, segment.SegmentParams(), None)
    n_true = len(session["truth"].rests)
    assert abs(out["rests"].num_rows - n_true) <= 4


def test_segmentation_noise_from_an_initial_rest(session):
    out = segment.STAGE.func(session["d"], segment.SegmentParams(initial_rest_s=60.0), None)
    assert abs(out["rests"].num_rows - len(session["truth"].rests)) <= 3


def test_thermal_k_recovered(session):
    truth = session["truth"].calibration
    for sensor in ("accel", "gyro", "mag"):
        t = one(session["th"]["calibration"], sensor)
        sd = np.array(t.details["sigma_k"])
        assert np.all(np.abs(t.k - truth[sensor].k) < K_TOL_SIGMA * sd + 1e-3 * np.abs(truth[sensor].k))


def test_thermal_poly_solver_is_interchangeable(session):
    th = thermal.STAGE.func({**session["d"], "rests": session["seg"]["rests"]},
                            thermal.ThermalParams(sensors=("gyro",)),
                            BoundSolver(ThermalPoly(), ThermalPolyParams(degree=1)))
    k = one(th["calibration"], "gyro").k
    assert np.allclose(k, one(session["th"]["calibration"], "gyro").k, rtol=0.05, atol=1e-6)


def test_accel_recovered(session):
    cal, true = one(session["ac"]["calibration"], "accel"), session["truth"].calibration["accel"]
    g = session["truth"].data["environment"]["g_m_s2"]
    assert np.all(np.abs(cal.b0 - true.b0) / g * 1e3 < ACC_BIAS_TOL_MG)
    assert np.abs(cal.M @ true.S - np.eye(3)).max() * 1e6 < ACC_M_TOL_PPM
    assert set(cal.details) >= {"sigma_M", "sigma_b0", "sigma_k", "covariance", "noise"}
    assert_within_sigma(cal, true)
    res = session["ac"]["residuals"]
    after = np.abs(res.column("norm_error_after").to_numpy())
    before = np.abs(res.column("norm_error_before").to_numpy())
    assert after.max() < 0.1 * before.max()


def test_mag_recovered_and_tied_to_accel(session):
    cal, true = one(session["mg"]["calibration"], "mag"), session["truth"].calibration["mag"]
    assert np.abs(cal.M @ true.S - np.eye(3)).max() < MAG_M_TOL
    assert abs(cal.details["dip_deg"] - session["truth"].data["environment"]["dip_deg"]) < 0.1
    assert_within_sigma(cal, true)


def test_gyro_recovered_in_accel_frame(session):
    cal, true = one(session["gy"]["calibration"], "gyro"), session["truth"].calibration["gyro"]
    assert np.abs(cal.M @ true.S - np.eye(3)).max() * 1e6 < GYRO_M_TOL_PPM
    assert np.all(np.degrees(np.abs(cal.b0 - true.b0)) < GYRO_BIAS_TOL_DPS)
    assert_within_sigma(cal, true)


def test_gyro_scale_from_the_detected_roll_turn(session):
    inputs = {"rests": session["seg"]["rests"], "turns": session["seg"]["turns"],
              "gyro": session["d"]["gyro"], "accel": session["ac"]["calibration"],
              "thermal": session["th"]["calibration"]}
    out = gyro.STAGE.func(inputs, gyro.GyroParams(detect_roll_turn=True),
                          BoundSolver(GyroRodrigues(), GyroRodriguesParams()))
    cal, true = one(out["calibration"], "gyro"), session["truth"].calibration["gyro"]
    assert cal.details["scale_from"] == "roll turn (eq. 37)"
    roll = session["truth"].segments(label="roll_turn")[0]
    turn_t = Turns.from_tables(session["seg"]["turns"], session["d"]["gyro"]).t
    j = next(i for i, t in enumerate(turn_t) if len(t) and t[0] <= roll["t_start_s"] + 1 <= t[-1])
    assert cal.details["roll_turn"] is not None and abs(cal.details["roll_turn"] - j) <= 2
    assert np.abs(cal.M @ true.S - np.eye(3)).max() * 1e6 < GYRO_M_TOL_PPM
    assert_within_sigma(cal, true)


def test_validation_improves_and_accepts(session):
    report = session["va"]["report"]
    summary = json.loads(report.schema.metadata[b"imupipe.summary"])
    assert summary["n_informative"] > 50
    assert summary["angle_error_rms_after_deg"] < 0.5 * summary["angle_error_rms_before_deg"]
    assert summary["passed"]


def test_turns_round_trip_through_tables(session):
    turns = Turns.from_tables(session["seg"]["turns"], session["d"]["gyro"])
    assert len(turns) == session["seg"]["turns"].num_rows
    assert all(len(t) == len(w) for t, w in zip(turns.t, turns.gyro, strict=True))
    # the turns' samples, copied once one after the other: no view keeps the whole recording's
    # (k, 3) copy alive, and the joint model's motion samples are these arrays, read-only
    g = session["d"]["gyro"]
    starts = np.searchsorted(g.column("t_ns").to_numpy(), session["seg"]["turns"].column("t_start_ns").to_numpy())
    held = sum(len(w) for w in turns.gyro)
    assert held < g.num_rows
    for i, w in zip(starts, turns.gyro, strict=True):
        assert w.base is turns.gyro[0].base and w.base.shape == (held, 3) and not w.flags.writeable
        assert np.array_equal(w, np.column_stack([g.column(c).to_numpy()[i:i + len(w)] for c in "xyz"]))
    samples = MotionSamples.from_turns(turns.t, turns.gyro)
    assert samples.y is turns.gyro[0].base and samples.t is turns.t[0].base
    assert np.array_equal(MotionSamples.from_turns(turns.t[1:], turns.gyro[1:]).y, np.concatenate(turns.gyro[1:]))


def test_accel_without_thermal_and_detected_references(session):
    out = accel.STAGE.func({"rests": session["seg"]["rests"]},
                           accel.AccelParams(detect_reference=True, detect_tol_deg=2.0),
                           BoundSolver(EllipsoidCholesky(), EllipsoidParams()))
    cal = one(out["calibration"], "accel")
    assert cal.details["reference_rests"]["how"] == "detected"
    assert np.allclose(cal.k, 0)


def test_too_few_rests_is_a_clear_error(session):
    rests = Rests.from_table(session["seg"]["rests"]).subset(np.arange(6))
    with pytest.raises(SolverError, match="rest positions"):
        accel.STAGE.func({"rests": rests.to_table()}, accel.AccelParams(),
                         BoundSolver(EllipsoidCholesky(), EllipsoidParams()))


def test_mag_dip_from_turntable_circles(session):
    truth = session["truth"]
    windows = tuple((s["t_start_s"], s["t_end_s"]) for s in truth.segments(label="turntable_turn"))
    assert len(windows) >= 2
    d = session["d"]
    out = mag.STAGE.func({"rests": session["seg"]["rests"], "accel": session["ac"]["calibration"],
                          "mag": d["mag"], "thermal": session["th"]["calibration"]},
                         mag.MagParams(circle_windows_s=windows), BoundSolver(MagDip(), MagDipParams()))
    cal = one(out["calibration"], "mag")
    assert cal.details["dip_source"] == "turntable circles"
    assert abs(cal.details["dip_deg"] - truth.data["environment"]["dip_deg"]) < 0.2
    assert abs(abs(np.linalg.det(cal.M)) - 1) < 1e-9  # tesla at the sensor's nominal scale


def test_thermal_without_warmup_errors_or_warns():
    rec, _ = simulate_recording("standard", None, 1, warmup_s=20, n_positions=30)
    d = dict(rec.device("imu"))
    seg = segment.STAGE.func(d, segment.SegmentParams(), None)
    solver = BoundSolver(ThermalKalman(), ThermalKalmanParams())
    with pytest.raises(SolverError, match="degC"):
        thermal.STAGE.func({**d, "rests": seg["rests"]}, thermal.ThermalParams(), solver)
    with pytest.warns(UserWarning, match="continuing with k = 0"):
        out = thermal.STAGE.func({**d, "rests": seg["rests"]},
                                 thermal.ThermalParams(on_insufficient="zero"), solver)
    assert all(not t.details["k_fitted"] and not t.k.any() for t in triads_from_table(out["calibration"]))

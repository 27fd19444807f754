"""Method A accuracy on simulated sessions, against the targets, from one run.

    /work/venv/bin/python bench/method_a_accuracy.py [--protocol sphere_rig] [--seed 0]

Simulates the session, runs the method A stages (segmentation, thermal Kalman
filter, accel ellipsoid with the reference rests, mag by the dip, gyro by
Rodrigues with exact rotations, turn validation), and prints each error beside
its target and the solver's own 1-sigma (the noise bound). Errors are those of
``imupipe.sim.compare`` (polar decomposition M S_true = Q H): scale = diag(H - I),
non-orthogonality = off-diagonal of H - I, alignment = angle of Q_acc^T Q_gyro,
mag shape = max |H - I| (field_T given, so with the scale).
"""

from __future__ import annotations

import argparse
import json
import time

from imupipe.components import BoundSolver
from imupipe.models import triads_from_table
from imupipe.sim.api import simulate_recording
from imupipe.sim.compare import calibration_errors, reported_sigma
from imupipe.solvers.ellipsoid_cholesky import EllipsoidCholesky, EllipsoidParams
from imupipe.solvers.gyro_rodrigues import GyroRodrigues, GyroRodriguesParams
from imupipe.solvers.mag_dip import MagDip, MagDipParams
from imupipe.solvers.thermal_kalman import ThermalKalman, ThermalKalmanParams
from imupipe.stages import accel, gyro, mag, segment, thermal, validate


def run(protocol: str, seed: int, exact: bool, scale_deg: float = 10.0, roll: bool = False) -> dict:
    rec, truth = simulate_recording(protocol, None, seed)
    d = dict(rec.device("imu"))
    env = truth.data["environment"]
    t0 = time.perf_counter()
    seg = segment.STAGE.func(d, segment.SegmentParams(), None)
    th = thermal.STAGE.func({**d, "rests": seg["rests"]}, thermal.ThermalParams(),
                            BoundSolver(ThermalKalman(), ThermalKalmanParams()))
    ref, rests = truth.reference_rests, truth.rests
    ac = accel.STAGE.func(
        {"rests": seg["rests"], "thermal": th["calibration"]},
        accel.AccelParams(g_m_s2=env["g_m_s2"], y_up_time_s=rests[ref["reference_y_up"]].mean(),
                          x_up_time_s=rests[ref["reference_x_up"]].mean()),
        BoundSolver(EllipsoidCholesky(), EllipsoidParams()))
    mg = mag.STAGE.func({"rests": seg["rests"], "accel": ac["calibration"], "mag": d["mag"],
                         "thermal": th["calibration"]}, mag.MagParams(field_T=env["field_T"]),
                        BoundSolver(MagDip(), MagDipParams()))
    gy = gyro.STAGE.func({"rests": seg["rests"], "turns": seg["turns"], "gyro": d["gyro"],
                          "accel": ac["calibration"], "thermal": th["calibration"]},
                         gyro.GyroParams(detect_roll_turn=roll), BoundSolver(GyroRodrigues(), GyroRodriguesParams(
                             exact_rotation=exact, max_scale_turn_deg=60.0 if exact else scale_deg)))
    va = validate.STAGE.func({"rests": seg["rests"], "turns": seg["turns"], "gyro": d["gyro"],
                              "accel": ac["calibration"], "gyro_cal": gy["calibration"]},
                             validate.ValidateParams(), None)
    elapsed = time.perf_counter() - t0
    cal = {t.sensor: t for tab in (ac, mg, gy) for t in triads_from_table(tab["calibration"])}
    return {"truth": truth, "cal": cal, "env": env, "elapsed": elapsed, "n_rests": seg["rests"].num_rows,
            "validation": json.loads(va["report"].schema.metadata[b"imupipe.summary"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--protocol", default="sphere_rig")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small-angle", action="store_true", help="the paper's eq. (29) instead of exact")
    ap.add_argument("--scale-turn-deg", type=float, default=10.0,
                    help="small-angle mode: largest turn used for the scale (as sphere-rig.toml)")
    ap.add_argument("--roll-turn", action="store_true",
                    help="gyro scale from the detected roll turn (eq. 37) instead of all turns")
    a = ap.parse_args()
    r = run(a.protocol, a.seed, not a.small_angle, a.scale_turn_deg, a.roll_turn)
    truth, cal, g = r["truth"].calibration, r["cal"], r["env"]["g_m_s2"]
    e = calibration_errors(cal, truth, g)
    sd = {s: reported_sigma(cal[s], g) for s in cal}
    rows = [
        ("accel bias", e["accel"].bias, sd["accel"]["bias"], 0.2, "mg"),
        ("accel scale", e["accel"].scale_ppm, sd["accel"]["scale_ppm"], 200, "ppm"),
        ("accel non-orthogonality", e["accel"].nonorth_ppm, sd["accel"]["nonorth_ppm"], 200, "ppm"),
        ("gyro scale", e["gyro"].scale_ppm, sd["gyro"]["scale_ppm"], 300, "ppm"),
        ("gyro non-orthogonality", e["gyro"].nonorth_ppm, sd["gyro"]["nonorth_ppm"], 300, "ppm"),
        ("gyro-to-accel alignment", e.gyro_accel_align_deg, sd["gyro"]["frame_deg"], 0.02, "deg"),
        ("mag shape", e["mag"].shape_ppm * 1e-4, sd["mag"]["nonorth_ppm"] * 1e-4, 0.2, "%"),
    ]
    print(f"method A on simulated '{a.protocol}' (seed {a.seed}), {r['n_rests']} rests, "
          f"gyro {'small-angle (eq. 29)' if a.small_angle else 'exact rotation'}, scale from "
          f"{cal['gyro'].details['scale_from']}, "
          f"stages {r['elapsed']:.1f} s")
    print(f"{'quantity':28s} {'error':>10s} {'1-sigma':>10s} {'target':>8s}  unit  met")
    for name, err, sd, target, unit in rows:
        print(f"{name:28s} {err:10.4g} {sd:10.3g} {target:8g}  {unit:4s}  {'yes' if err <= target else 'NO'}")
    v = r["validation"]
    print(f"turn-angle error RMS: before {v['angle_error_rms_before_deg']:.4f} deg, after "
          f"{v['angle_error_rms_after_deg']:.4f} deg (max {v['angle_error_max_after_deg']:.4f}); "
          f"{v['n_accepted']}/{v['n_informative']} turns < {v['tolerance_deg']} deg")
    print(f"mag dip: {cal['mag'].details['dip_deg']:.3f} deg (true {r['env']['dip_deg']}), "
          f"source: {cal['mag'].details['dip_source']}")


if __name__ == "__main__":
    main()

"""imupipe on tomisuarez2/ImuCalibration's MPU-6050 session: ten poses, a clipping gyro.

    /work/venv/bin/python bench/peers_tomisuarez2.py

Ten short hand-placed poses after an initial rest: one more than method B's
nine accelerometer constants, so the fit is possible but cannot check itself.
The gyro clips at +-250 deg/s during some turns. Shown:

- the rests found (accelerometer-only stillness, as imu_tk and tomisuarez2 do:
  this unit's gyro is not quiet enough at the poses for the joint test);
- the accelerometer by ``ellipsoid_svd`` with its 1-sigma and the degrees of
  freedom left, and how many positions a checked fit needs;
- the gyroscope by ``gyro_integration``: clipped turns detected (from the data,
  and from the known range) and left out with a warning, the fit on the rest;
- both beside that repository's published parameters (``optmization result data``).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from imupipe.errors import SolverError
from imupipe.ingest import read_recording
from imupipe.models import TriadCalibration
from imupipe.observations import EllipsoidObservations, GyroObservations, Rests, Turns
from imupipe.plugins import make_registry
from imupipe.solvers.ellipsoid_svd import EllipsoidSVD, EllipsoidSVDParams
from imupipe.solvers.gyro_integration import GyroIntegration, GyroIntegrationParams, saturated_turns
from imupipe.stages.segment import SegmentParams, segment

REPO = Path(__file__).resolve().parents[1]
SESSION = REPO / "examples" / "sessions" / "tomisuarez2.toml"
PUBLISHED = REPO.parent / "shared" / "data" / "tomisuarez2_mpu6050" / "optmization result data"
G = 9.80665
SEGMENT = SegmentParams(window_s=0.5, initial_rest_s=36.5, accel_threshold=10.0, gyro_threshold=1e9,
                        min_rest_s=0.5)
CHECKED_FIT_POSITIONS = 20  # rests for a residual check worth the name (method A's paper: >= 200)
ACC_LSB = G / 16384.0  # m/s^2 per count (+-2 g)
GYR_LSB = np.radians(1.0) / 131.0  # rad/s per count (+-250 deg/s)


def published() -> dict[str, np.ndarray]:
    """That repository's parameters: misalignments (3 / 6), scales per count, biases in counts."""
    acc = np.loadtxt(PUBLISHED / "params_acc.csv")
    gyr = np.loadtxt(PUBLISHED / "params_gyro.csv")
    return {"acc_scale": acc[3:6] / ACC_LSB, "acc_bias": acc[6:9] * ACC_LSB,
            "gyr_scale": gyr[6:9] / GYR_LSB, "gyr_bias": gyr[9:12] * GYR_LSB}


def main() -> None:
    dev = read_recording(SESSION, make_registry()).device()
    seg = segment(dict(dev), SEGMENT, None)
    rests = Rests.from_table(seg["rests"])
    turns = Turns.from_tables(seg["turns"], dev["gyro"], rests.t0_ns)
    pub = published()
    dur = rests.t_end_s - rests.t_start_s
    print(f"tomisuarez2 MPU-6050: {len(rests)} rests (initial {dur[0]:.1f} s, poses "
          f"{dur[1:].min():.1f}-{dur[1:].max():.1f} s), {len(turns)} turns")

    print("\nAccelerometer (ellipsoid_svd, 9 constants)")
    obs = EllipsoidObservations("accel", rests.mean["accel"], rests.cov_of_mean("accel"), rests.temperature, G)
    try:
        fit = EllipsoidSVD().solve(obs, EllipsoidSVDParams())
    except SolverError as exc:
        print(f"  {exc}")
        return
    sd = np.sqrt(np.diag(fit.cov))
    dof = fit.details["dof"]
    print(f"  correction diagonal (true per raw) {np.round(np.diag(fit.M), 5)} +- {np.round(sd[[0, 4, 8]], 5)}"
          f"   published {np.round(pub['acc_scale'], 5)}")
    print(f"  bias {np.round(fit.b0, 4)} +- {np.round(sd[9:], 4)} m/s^2   published, negated (that "
          f"model adds its accelerometer b) {np.round(-pub['acc_bias'], 4)}")
    print(f"  |g| residual RMS {fit.details['rms_residual'] * 1e3:.1f} mm/s^2 over {len(rests)} rests, "
          f"dof {dof}, chi2/dof {fit.details['chi2'] / max(dof, 1):.0f} (sigmas inflated by it)")
    if dof < CHECKED_FIT_POSITIONS - 9:
        print(f"  -> {dof} spare position(s): the fit cannot test itself; the sigmas rest on "
              f"{dof} degree(s) of freedom. Record at least {CHECKED_FIT_POSITIONS - len(rests)} more "
              f"distinct positions ({CHECKED_FIT_POSITIONS} in all) for a checked calibration.")
    accel = TriadCalibration("accel", fit.M, fit.b0)

    print("\nGyroscope (gyro_integration)")
    bad, n_sat, axes = saturated_turns(turns)
    bad_r, n_sat_r, _ = saturated_turns(turns, np.radians(250.0))
    print(f"  clipping from the data: {n_sat} samples on axes {', '.join(axes)} in {int(bad.sum())} turns; "
          f"from the +-250 deg/s range: {n_sat_r} samples in {int(bad_r.sum())} turns")
    g = accel.apply(rests.mean["accel"])
    gobs = GyroObservations(g / np.linalg.norm(g, axis=1, keepdims=True), rests.mean["gyro"],
                            rests.cov_of_mean("gyro"), turns)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            gf = GyroIntegration().solve(gobs, GyroIntegrationParams())
        except SolverError as exc:
            print(f"  {exc}")
            gf = None
    for w in caught:
        print(f"  warning: {w.message}")
    if gf is None:
        return
    sd = np.sqrt(np.diag(gf.cov))
    used = gf.details["turns"]
    print(f"  correction diagonal {np.round(np.diag(gf.M), 4)} +- {np.round(sd[[0, 4, 8]], 4)}"
          f"   published {np.round(pub['gyr_scale'], 4)}")
    print(f"  bias {np.round(np.degrees(gf.b0), 3)} deg/s   published {np.round(np.degrees(pub['gyr_bias']), 3)}")
    print(f"  gravity mismatch after the turns: RMS {gf.details['rms_gravity_mismatch_deg']:.2f} deg over "
          f"{used} turns ({2 * used - 9} dof)")
    if 2 * used - 9 < 2 * 10:
        print(f"  -> {used} usable turns for 9 constants: sigmas from {2 * used - 9} dof only; record "
              f"{max(0, 15 - used)} more unclipped turns about all axes (15 or more) for a checked fit.")


if __name__ == "__main__":
    main()

"""Method A on real recordings: |g| and turn-angle errors before and after calibration.

    /work/venv/bin/python bench/real_data_method_a.py

Datasets (../shared/data): sunsided MPU6050 + HMC5883L full-sphere tumbling
(MATLAB v7.3 buffers, read with imupipe's matlab reader), and imu_tk's Xsens
sample (ASCII counts, converted with the nominal Xsens factors 414 counts per
m/s^2 and 4770 counts per rad/s around 32768; the calibration absorbs the rest).
No reference rests are known, so the accelerometer frame is the symmetric
canonical one; g = 9.80665. A recording that cannot support the method prints
the solver's reason instead of numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa

from imupipe import schemas
from imupipe.components import BoundSolver
from imupipe.errors import ImupipeError
from imupipe.models import triads_from_table
from imupipe.readers.matlab import MatlabReader
from imupipe.solvers.ellipsoid_cholesky import EllipsoidCholesky, EllipsoidParams
from imupipe.solvers.gyro_rodrigues import GyroRodrigues, GyroRodriguesParams
from imupipe.solvers.mag_dip import MagDip, MagDipParams
from imupipe.stages import accel, gyro, mag, segment, validate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SUNSIDED = DATA / "sunsided_mpu6050_hmc5883l" / "data" / "set-2" / "full-sphere"
XSENS = DATA / "imu_tk_xsens"


def sunsided() -> dict[str, pa.Table]:
    tables: dict[str, pa.Table] = {}
    for f in sorted(SUNSIDED.glob("*.mat")):
        tables.update(MatlabReader().read(f).devices["imu"])
    return tables


def xsens() -> dict[str, pa.Table]:
    out = {}
    for stream, name, per_si in (("accel", "xsens_acc.mat", 414.0), ("gyro", "xsens_gyro.mat", 4770.0)):
        a = np.loadtxt(XSENS / name)
        cols = {"t_ns": np.round(a[:, 0] * 1e9).astype(np.int64)}
        cols.update({c: (a[:, i + 1] - 32768.0) / per_si for i, c in enumerate("xyz")})
        out[stream] = schemas.stamp(pa.table(cols), stream)
    return out


# imu_tk's printed result for its Xsens sample (../shared/data/README.md): calib = T K (raw - b)
IMU_TK_ACC_T = np.array([[1, -0.0033593, -0.00890639], [0, 1, -0.0213341], [0, 0, 1]])
IMU_TK_ACC_K = 1 / np.array([414.459, 412.01, 414.649])
IMU_TK_GYR_T = np.array([[1, 0.00593634, 0.00111101], [0.00808812, 1, -0.0535569],
                         [0.0253067, -0.0025513, 1]])
IMU_TK_GYR_K = 1 / np.array([4777.96, 4764.21, 4773.66])


def compare_imu_tk(acc, gyr) -> None:
    """imu_tk's gyro matrix carried into our accelerometer frame, beside ours."""
    A_tk = IMU_TK_ACC_T @ np.diag(IMU_TK_ACC_K) * 414.0  # per nominal SI unit of our tables
    G_tk = IMU_TK_GYR_T @ np.diag(IMU_TK_GYR_K) * 4770.0
    U, _, Vt = np.linalg.svd(acc.M @ np.linalg.inv(A_tk))
    R = U @ Vt  # rotation from imu_tk's accel frame to ours
    G_in_ours = R @ G_tk
    print(f"  vs imu_tk (in our accel frame): max |M_gyro - M_imu_tk| = "
          f"{np.abs(gyr.M - G_in_ours).max():.4f}; diag ours {np.round(np.diag(gyr.M), 4).tolist()}, "
          f"imu_tk {np.round(np.diag(G_in_ours), 4).tolist()}; accel max |diff| "
          f"{np.abs(acc.M - R @ A_tk).max():.4f}")


def calibrate(tables: dict[str, pa.Table], seg_params: segment.SegmentParams,
              peer: bool = False) -> None:
    seg = segment.STAGE.func(tables, seg_params, None)
    n_rests = seg["rests"].num_rows
    angles = seg["turns"].column("angle_deg").to_numpy()
    print(f"  segmentation: {n_rests} rests, {len(angles)} turns "
          f"(median turn {np.median(angles) if len(angles) else float('nan'):.1f} deg)")
    try:
        ac = accel.STAGE.func({"rests": seg["rests"]}, accel.AccelParams(),
                              BoundSolver(EllipsoidCholesky(), EllipsoidParams()))
    except ImupipeError as exc:
        print(f"  accel: cannot calibrate: {exc}")
        return
    res = ac["residuals"]
    before = res.column("norm_error_before").to_numpy() * 1e3
    after = res.column("norm_error_after").to_numpy() * 1e3
    print(f"  accel |g| error (per mille of g): before RMS {np.sqrt(np.mean(before**2)):.2f} "
          f"max {np.abs(before).max():.2f}; after RMS {np.sqrt(np.mean(after**2)):.3f} "
          f"max {np.abs(after).max():.3f}")
    cal = triads_from_table(ac["calibration"])[0]
    print(f"  accel b0 = {np.round(cal.b0, 4).tolist()} m/s^2, "
          f"diag(M) = {np.round(np.diag(cal.M), 5).tolist()}")
    if "mag" in tables:
        try:
            mg = mag.STAGE.func({"rests": seg["rests"], "accel": ac["calibration"], "mag": tables["mag"]},
                                mag.MagParams(), BoundSolver(MagDip(), MagDipParams()))
            r = mg["residuals"].column("norm_error_after").to_numpy()
            b = mg["residuals"].column("norm_error_before").to_numpy()
            m = triads_from_table(mg["calibration"])[0]
            print(f"  mag normalised |B| error: before max {np.abs(b).max():.3f}, after max "
                  f"{np.abs(r).max():.4f}; dip {m.details['dip_deg']:.1f} deg ({m.details['dip_source']})")
        except ImupipeError as exc:
            print(f"  mag: cannot calibrate: {exc}")
    try:
        gy = gyro.STAGE.func({"rests": seg["rests"], "turns": seg["turns"], "gyro": tables["gyro"],
                              "accel": ac["calibration"]}, gyro.GyroParams(),
                             BoundSolver(GyroRodrigues(), GyroRodriguesParams()))
    except ImupipeError as exc:
        print(f"  gyro: cannot calibrate: {exc}")
        return
    g = triads_from_table(gy["calibration"])[0]
    print(f"  gyro diag(M) = {np.round(np.diag(g.M), 5).tolist()}, turns used "
          f"{g.details['n_turns_used']}/{g.details['n_turns']}")
    va = validate.STAGE.func({"rests": seg["rests"], "turns": seg["turns"], "gyro": tables["gyro"],
                              "accel": ac["calibration"], "gyro_cal": gy["calibration"]},
                             validate.ValidateParams(), None)
    s = json.loads(va["report"].schema.metadata[b"imupipe.summary"])
    print(f"  gravity carried through each turn by the gyro, error RMS (in-sample): before "
          f"{s['gravity_error_rms_before_deg']:.3f} deg, after {s['gravity_error_rms_after_deg']:.3f} deg")
    print(f"  eq. (39) turn-angle error RMS over turns <= 60 deg: before "
          f"{s['angle_error_rms_before_deg']:.3f} deg, after {s['angle_error_rms_after_deg']:.3f} deg; "
          f"{s['n_accepted']}/{s['n_informative']} turns < {s['tolerance_deg']} deg")
    if peer:
        compare_imu_tk(cal, g)


def main() -> None:
    print("sunsided MPU6050 + HMC5883L, set-2/full-sphere")
    calibrate(sunsided(), segment.SegmentParams(min_rest_s=1.0))
    print("imu_tk Xsens MTi sample (nominal count factors)")
    calibrate(xsens(), segment.SegmentParams(initial_rest_s=50.0, min_rest_s=1.0), peer=True)


if __name__ == "__main__":
    main()

"""imupipe beside imucal on imucal's own Ferraris session (shared/data/imucal).

    /work/venv/bin/python bench/peers_imucal.py

The session (``examples/sessions/imucal_ferraris.toml``) holds six static poses
(each axis up and down) and three 360 deg turns about the vertical, with
imucal's section list. What imupipe can and cannot take from it:

- accelerometer: six orientations cannot fix the nine constants of method B's
  quadric (the solver says how many more are needed); the axis-aligned quadric
  (``ellipsoid_svd`` with ``misalignment = false``: three scales, three biases)
  is fitted instead, from the six pose means;
- gyroscope: gravity does not move during a turn about the vertical, so method
  B's gravity mismatch carries no information on these turns (the solver
  refuses); the bias is Eq. (2.15) over the six poses, and the scale comes from
  the protocol's known angle (-360 deg, the manifest's ``turn_angle_deg``): the
  bias-removed rate integrated over each turn section, divided by the angle;
- then imupipe's calibration is applied to the first 50 raw rows and compared
  with imucal's calibrated rows (``ferraris_example.csv``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imupipe.errors import SolverError
from imupipe.ingest import read_recording
from imupipe.models import TriadCalibration
from imupipe.observations import EllipsoidObservations, GyroObservations, Turns
from imupipe.plugins import make_registry
from imupipe.solvers.ellipsoid_svd import EllipsoidSVD, EllipsoidSVDParams
from imupipe.solvers.gyro_integration import GyroIntegration, GyroIntegrationParams

REPO = Path(__file__).resolve().parents[1]
SESSION = REPO / "examples" / "sessions" / "imucal_ferraris.toml"
SNAPSHOT = REPO.parent / "shared" / "data" / "imucal" / "ferraris_example.csv"
POSES = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
TURNS = ("x_rot", "y_rot", "z_rot")
G = 9.81  # imucal's setting
IMUCAL = {"accel_scale": [0.99675, 1.00244, 1.02340], "accel_bias": [0.537, -0.616, 0.399],
          "gyro_scale": [1.02792, 0.98243, 0.99831], "gyro_bias_dps": [-0.600, -0.370, 0.059]}


def xyz(table) -> np.ndarray:
    return np.column_stack([table.column(c).to_numpy() for c in ("x", "y", "z")])


def main() -> None:
    rec = read_recording(SESSION, make_registry())
    dev = rec.device()
    acc, gyr = xyz(dev["accel"]), xyz(dev["gyro"])
    t = dev["gyro"].column("t_ns").to_numpy() * 1e-9
    sec = rec.meta["sections"]
    angle = np.radians(rec.meta["meta"]["turn_angle_deg"])
    pose = [slice(sec[p]["start"], sec[p]["end"]) for p in POSES]
    y = np.array([acc[s].mean(axis=0) for s in pose])
    cov = np.array([np.cov(acc[s].T) / (s.stop - s.start) for s in pose])
    obs = EllipsoidObservations("accel", y, cov, np.full(6, np.nan), G)

    print("Accelerometer (six pose means, g = 9.81)")
    try:
        EllipsoidSVD().solve(obs, EllipsoidSVDParams())
    except SolverError as exc:
        print(f"  method B, 9 constants: {exc}")
    fit = EllipsoidSVD().solve(obs, EllipsoidSVDParams(misalignment=False))
    sd = np.sqrt(np.diag(fit.cov))
    scale = 1.0 / np.diag(fit.M)
    sd_scale = sd[[0, 4, 8]] * scale**2
    print("  axis-aligned quadric (3 scales + 3 biases), 1-sigma from the fit:")
    print(f"    scale  imupipe {np.round(scale, 5)} +- {np.round(sd_scale, 5)}   imucal {IMUCAL['accel_scale']}")
    print(f"    bias   imupipe {np.round(fit.b0, 3)} +- {np.round(sd[9:], 3)} m/s^2   imucal {IMUCAL['accel_bias']}")
    print(f"    |g| residual RMS over the poses {fit.details['rms_residual']:.4f} m/s^2, chi2/dof "
          f"{fit.details['chi2'] / max(fit.details['dof'], 1):.1f} (dof {fit.details['dof']})")
    accel = TriadCalibration("accel", fit.M, fit.b0)

    print("\nGyroscope (the reader gives rad/s; shown in deg/s)")
    rest_bias = np.array([gyr[s].mean(axis=0) for s in pose])
    b_g = rest_bias.mean(axis=0)  # Eq. (2.15)
    g_dir = accel.apply(y)
    g_dir /= np.linalg.norm(g_dir, axis=1, keepdims=True)
    turn = [slice(sec[k]["start"], sec[k]["end"]) for k in TURNS]
    # Gravity before and after each 360 deg turn: the pose rest nearest in time is not
    # the same orientation here, so use the turn's own first and last second.
    ends = []
    for s in turn:
        a0 = acc[s.start - 100: s.start].mean(axis=0)
        a1 = acc[s.stop: s.stop + 100].mean(axis=0)
        ends.append((a0, a1))
    g_turn = accel.apply(np.array([v for pair in ends for v in pair]))
    g_turn /= np.linalg.norm(g_turn, axis=1, keepdims=True)
    tilt = np.degrees(np.arccos(np.clip(np.sum(g_turn[0::2] * g_turn[1::2], axis=1), -1, 1)))
    print(f"  gravity moves by {np.round(tilt, 2)} deg over the three turns: no information for "
          "method B's gravity mismatch")
    turns = Turns(np.array([0, 2, 4]), np.array([1, 3, 5]), tuple(t[s] for s in turn),
                  tuple(gyr[s] for s in turn))
    try:
        GyroIntegration().solve(GyroObservations(g_turn, np.tile(b_g, (6, 1)),
                                                 np.tile(np.eye(3) * 1e-10, (6, 1, 1)), turns),
                                GyroIntegrationParams())
        print("  gyro_integration ran (unexpected on vertical turns)")
    except SolverError as exc:
        print(f"  method B: {exc}")
    # Known-angle scale: the bias-removed rate integrated over each turn, Sigma_j = S e_j angle.
    cols = [np.sum((gyr[s] - b_g) * np.gradient(t[s])[:, None], axis=0) / angle for s in turn]
    S_g = np.column_stack(cols)
    print(f"  scale (known -360 deg turns) imupipe {np.round(np.diag(S_g), 5)}   imucal {IMUCAL['gyro_scale']}")
    print(f"  bias, Eq. (2.15) over the poses imupipe {np.round(np.degrees(b_g), 3)}   "
          f"imucal {IMUCAL['gyro_bias_dps']}")
    print(f"  off-diagonal of S (misalignment + the turns' tilt) {np.round(S_g[~np.eye(3, dtype=bool)], 4)}")

    print("\nFirst 50 calibrated rows beside imucal's ferraris_example.csv")
    ref = np.genfromtxt(SNAPSHOT, delimiter=",", names=True)
    ref_acc = np.column_stack([ref[f"acc_{a}"] for a in "xyz"])
    ref_gyr = np.column_stack([ref[f"gyr_{a}"] for a in "xyz"])
    n = len(ref)
    mine_acc = accel.apply(acc[:n])
    mine_gyr = np.degrees((gyr[:n] - b_g) @ np.linalg.inv(S_g).T)
    for name, mine, theirs, unit in (("accel", mine_acc, ref_acc, "m/s^2"), ("gyro", mine_gyr, ref_gyr, "deg/s")):
        d = mine - theirs
        print(f"  {name}: RMS difference per axis {np.round(np.sqrt(np.mean(d**2, axis=0)), 4)} {unit}; "
              f"mean difference {np.round(d.mean(axis=0), 4)}; imucal's own RMS about its mean "
              f"{np.round(theirs.std(axis=0), 4)}")
    print("  (imucal also turns the accelerometer by its misalignment R_a, which six poses give only\n"
          "   by assuming each pose is exactly axis-up: the accel difference in y, z is that rotation)")


if __name__ == "__main__":
    main()

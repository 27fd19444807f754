"""imupipe beside imu_tk on imu_tk's own Xsens recording (shared/data/imu_tk_xsens).

    /work/venv/bin/python bench/peers_imu_tk.py [--every 4] [--repeat 3]

Reads the session manifest ``examples/sessions/imu_tk_xsens.toml`` (raw counts
presented as if SI, so M comes out in SI per count and b0 in counts), segments
with imu_tk's test-program settings (1 s = 100-sample windows, 50 s initial
rest, threshold 4x its variance), and calibrates with method B
(``ellipsoid_svd`` + ``gyro_integration``, g = 9.81744) and the joint
refinement. Prints:

1. scales in counts per unit and misalignments in imu_tk's own gauge
   (``calib = T K (raw - b)``, T upper unit-triangular for the accelerometer)
   beside imu_tk's printed values and the Xsens factory scales;
2. the control-set gravity error: every ``every``-th turn is held out with its
   two rests (strict), or only the turn (rests shared), or nothing (in-sample);
   imupipe fits on what is left; imu_tk's printed parameters (fitted on all
   data) and imupipe's are judged by the same code
   (``imupipe.stages.control.control_errors``);
   ``bias = adjacent_rests`` (each turn uses its two rests' mean: this unit's gyro
   bias wanders between rests by ~5 counts, 4x the noise of a rest mean) is shown too;
3. imupipe's calibration time (segmentation + solvers, best of ``repeat``) beside
   imu_tk's 1.0 s;
4. whole processes as a user runs them, best of ``repeat`` (each in a fresh output
   folder, nothing cached): ``imupipe run`` with ``pipelines/imu_tk.toml`` without its
   report (calibration only), with it, and the default pipeline (the SI manifest),
   beside imu_tk's ``test_imu_calib`` on the same two files: run here when
   ``$IMU_TK_BIN`` names a built ``test_imu_calib``, else its published 1.0 s. Wall,
   CPU and peak memory of each, and the ratios (targets: <= 1.0x without the report,
   <= 1.5x with it). The bytecode of ``imupipe/`` and ``plugins/`` is compiled first, as
   ``pip install`` does: a user's process loads ``.pyc`` files, where
   ``PYTHONDONTWRITEBYTECODE`` would make every timed process compile imupipe's sources
   again (~0.1 s).

``--process-only`` prints section 4 alone.

Building ``test_imu_calib`` (as done to measure it; its sources are not part of imupipe): Debian's
``libceres-dev`` and ``libeigen3-dev``, imu_tk's ``include/``, ``src/{calibration,filters,io_utils}.cpp``
and ``apps/test_imu_calib.cpp`` (upstream, bitbucket.org/alberto_pretto/imu_tk, or a mirror),
with ``include/imu_tk/visualization.h`` replaced by no-op plots (its verbose output would draw
with gnuplot and wait for a key), then ``g++ -O3 -DNDEBUG -std=c++17 -I include
-I /usr/include/eigen3 apps/test_imu_calib.cpp src/*.cpp -lceres -lglog``. It prints the 1/K
imu_tk published to 0.002 %.
"""

from __future__ import annotations

import argparse
import compileall
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from imupipe.ingest import read_recording
from imupipe.models import TriadCalibration
from imupipe.observations import EllipsoidObservations, GyroObservations, Rests, Turns
from imupipe.plugins import make_registry
from imupipe.solvers.ellipsoid_svd import EllipsoidSVD, EllipsoidSVDParams
from imupipe.solvers.gyro_integration import GyroIntegration, GyroIntegrationParams
from imupipe.solvers.joint_ml import JointML, JointMLParams, JointObservations
from imupipe.stages.control import control_errors
from imupipe.stages.segment import SegmentParams, segment

REPO = Path(__file__).resolve().parents[1]
SESSION = REPO / "examples" / "sessions" / "imu_tk_xsens.toml"
SESSION_SI = REPO / "examples" / "sessions" / "imu_tk_xsens_si.toml"
DATA = REPO.parent / "shared" / "data" / "imu_tk_xsens"
IMU_TK_BIN_ENV = "IMU_TK_BIN"
G = 9.81744
SEGMENT = SegmentParams(window_s=1.0, initial_rest_s=50.0, accel_threshold=4.0, gyro_threshold=4.0,
                        min_rest_s=2.0)

# imu_tk's printed result (data/README.md): calib = T K (raw - b), counts.
IMU_TK = {
    "accel": {"T": [[1, -0.0033593, -0.00890639], [0, 1, -0.0213341], [0, 0, 1]],
              "invK": [414.459, 412.01, 414.649], "b": [33124.2, 33275.2, 32364.4]},
    "gyro": {"T": [[1, 0.00593634, 0.00111101], [0.00808812, 1, -0.0535569], [0.0253067, -0.0025513, 1]],
             "invK": [4777.96, 4764.21, 4773.66], "b": [32777.1, 32459.8, 32511.8]},
}
IMU_TK_SECONDS = 1.0
XSENS_FACTORY = {"accel": [415, 413, 415], "gyro": [4778, 4758, 4766]}


def imu_tk_calibration(sensor: str) -> TriadCalibration:
    p = IMU_TK[sensor]
    M = np.array(p["T"]) @ np.diag(1.0 / np.array(p["invK"]))
    return TriadCalibration(sensor, M, np.array(p["b"]), solver="imu_tk (printed)")


def imu_tk_gauge(accel: TriadCalibration, gyro: TriadCalibration) -> dict[str, dict[str, np.ndarray]]:
    """imupipe's answer re-expressed as imu_tk's ``T K``: the accel correction made upper-triangular.

    ``M_a = Q R`` (QR, positive diagonal): the frame turned by ``Q^T`` gives ``R``;
    the gyro, which lives in the accelerometer's frame, turns with it.
    """
    Q, R = np.linalg.qr(accel.M)
    D = np.diag(np.sign(np.diag(R)))
    Q, R = Q @ D, D @ R
    out = {}
    for sensor, M in (("accel", R), ("gyro", Q.T @ gyro.M)):
        K = np.diag(M).copy()
        out[sensor] = {"T": M / K[None, :], "invK": 1.0 / K}
    return out


def calibrate(rests: Rests, turns: Turns, joint: bool,
              bias: str = "all_rests") -> tuple[TriadCalibration, TriadCalibration]:
    af = EllipsoidSVD().solve(EllipsoidObservations("accel", rests.mean["accel"], rests.cov_of_mean("accel"),
                                                    rests.temperature, G), EllipsoidSVDParams())
    accel = TriadCalibration("accel", af.M, af.b0, solver="ellipsoid_svd")
    g = accel.apply(rests.mean["accel"])
    gf = GyroIntegration().solve(GyroObservations(g / np.linalg.norm(g, axis=1, keepdims=True),
                                                  rests.mean["gyro"], rests.cov_of_mean("gyro"), turns),
                                 GyroIntegrationParams(bias=bias))
    gyro = TriadCalibration("gyro", gf.M, gf.b0, solver="gyro_integration")
    if not joint:
        return accel, gyro
    fit = JointML().solve(JointObservations(rests, turns, G, accel, gyro), JointMLParams())
    return (TriadCalibration("accel", fit.triads["accel"].M, fit.triads["accel"].b0, solver="joint_ml"),
            TriadCalibration("gyro", fit.triads["gyro"].M, fit.triads["gyro"].b0, solver="joint_ml"))


def split(rests: Rests, turns: Turns, every: int):
    """Control: every ``every``-th turn and its two rests; calibration: rests and turns not touching them."""
    m = len(turns)
    ctl_turn = (np.arange(m) % every) == every - 1
    ctl_rest = np.zeros(len(rests), bool)
    ctl_rest[turns.before[ctl_turn]] = True
    ctl_rest[turns.after[ctl_turn]] = True
    cal_rest = ~ctl_rest
    new = np.cumsum(cal_rest) - 1
    keep = cal_rest[turns.before] & cal_rest[turns.after]
    idx = np.flatnonzero(keep)
    cal_turns = Turns(new[turns.before[idx]], new[turns.after[idx]],
                      tuple(turns.t[i] for i in idx), tuple(turns.gyro[i] for i in idx))
    return rests.subset(cal_rest), cal_turns, turns.subset(ctl_turn)


def measure(cmd: list[str], repeat: int, fresh: Path | None = None, cwd: Path | None = None) -> dict[str, float]:
    """Best of ``repeat`` runs of ``cmd``: wall s, CPU s (user + sys of the child), peak MiB.

    ``fresh``: a folder emptied before every run (the output folder: nothing cached); ``cwd``:
    the child's working folder.
    """
    best: dict[str, float] = {}
    for _ in range(repeat):
        if fresh is not None:
            shutil.rmtree(fresh, ignore_errors=True)
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        err = proc.stderr.read()
        if os.waitstatus_to_exitcode(status):
            sys.exit(f"{' '.join(map(str, cmd))} failed:\n{err}")
        run = {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "mib": usage.ru_maxrss / 1024}
        if not best or run["wall"] < best["wall"]:
            best = run
    return best


def whole_process(repeat: int) -> Callable[[], None]:
    """Section 4: ``imupipe run`` as whole processes beside imu_tk's test program, measured now
    (while this process is small: a child's peak RSS counts what it was forked from) and printed
    by the function returned."""
    for package in (REPO / "imupipe", REPO / "plugins"):
        compileall.compile_dir(package, quiet=1)
    tmp = Path(tempfile.mkdtemp(prefix="imupipe-peers-imu_tk-"))
    try:
        without_report = tmp / "imu_tk_no_report.toml"
        text = (REPO / "pipelines" / "imu_tk.toml").read_text()
        without_report.write_text("\n".join(line for line in text.splitlines()
                                            if not line.startswith("reports = ")) + "\n")
        imupipe = [sys.executable, "-m", "imupipe", "run", "--quiet", "--out", str(tmp / "out")]
        rows = {
            "imu_tk.toml without report": measure(
                [*imupipe, str(SESSION), "--pipeline", str(without_report)], repeat, tmp / "out"),
            "imu_tk.toml with report": measure(
                [*imupipe, str(SESSION), "--pipeline", str(REPO / "pipelines" / "imu_tk.toml")],
                repeat, tmp / "out"),
            "default pipeline (SI manifest)": measure([*imupipe, str(SESSION_SI)], repeat, tmp / "out"),
        }
        binary = os.environ.get(IMU_TK_BIN_ENV)
        if binary:
            # in the temporary folder: it writes test_imu_acc.calib and test_imu_gyro.calib there
            ref = measure([binary, str(DATA / "xsens_acc.mat"), str(DATA / "xsens_gyro.mat")], repeat, cwd=tmp)
            source = f"imu_tk {binary} run here"
        else:
            # its test program runs on one core: the published time stands for its CPU too
            ref = {"wall": IMU_TK_SECONDS, "cpu": IMU_TK_SECONDS, "mib": float("nan")}
            source = (f"imu_tk's published {IMU_TK_SECONDS} s, wall and CPU (set ${IMU_TK_BIN_ENV} "
                      "to a built test_imu_calib to run it here)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    floor = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return lambda: _print_whole_process(repeat, rows, ref, source, floor)


def _print_whole_process(repeat: int, rows: dict, ref: dict, source: str, floor: float) -> None:
    print(f"\n4. Whole process, best of {repeat} (fresh output folder, nothing cached), vs {source}; "
          f"a child's peak MiB counts this bench's own size when it forked (up to {floor:.0f} MiB; "
          "farm-bench's figures are exact)")
    print(f"   {'':40s} {'wall s':>7s} {'CPU s':>7s} {'peak MiB':>8s} {'wall ratio':>10s} {'CPU ratio':>9s}")
    print(f"   {'imu_tk test_imu_calib':40s} {ref['wall']:7.2f} {ref['cpu']:7.2f} {ref['mib']:8.0f}")
    targets = {"imu_tk.toml without report": 1.0, "imu_tk.toml with report": 1.5}
    for name, r in rows.items():
        target = f"  (target <= {targets[name]}x)" if name in targets else ""
        print(f"   {'imupipe ' + name:40s} {r['wall']:7.2f} {r['cpu']:7.2f} {r['mib']:8.0f} "
              f"{r['wall'] / ref['wall']:9.2f}x {r['cpu'] / ref['cpu']:8.2f}x{target}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--process-only", action="store_true", help="only section 4 (whole processes)")
    args = ap.parse_args()
    print_processes = whole_process(args.repeat)
    if args.process_only:
        print_processes()
        return
    t = time.perf_counter()
    dev = read_recording(SESSION, make_registry()).device()
    t_read = time.perf_counter() - t

    def run(joint: bool):
        seg = segment(dict(dev), SEGMENT, None)
        rests = Rests.from_table(seg["rests"])
        turns = Turns.from_tables(seg["turns"], dev["gyro"], rests.t0_ns)
        return rests, turns, calibrate(rests, turns, joint)

    timings = {}
    for joint in (False, True):
        best = np.inf
        for _ in range(args.repeat):
            t = time.perf_counter()
            rests, turns, cal = run(joint)
            best = min(best, time.perf_counter() - t)
        timings[joint] = (best, cal)
    print(f"imu_tk_xsens: {len(rests)} static intervals ({len(turns)} rotations); imu_tk found 38 (37)")

    print("\n1. Scales [counts per m/s^2 | counts per rad/s] and misalignment, imu_tk's gauge")
    tk = {s: {"T": np.array(IMU_TK[s]["T"]), "invK": np.array(IMU_TK[s]["invK"])} for s in ("accel", "gyro")}
    mine = {"B": imu_tk_gauge(*timings[False][1]), "joint": imu_tk_gauge(*timings[True][1])}
    for sensor in ("accel", "gyro"):
        print(f"  {sensor}: 1/K")
        print(f"    imu_tk         {np.round(tk[sensor]['invK'], 2)}")
        for name, g in mine.items():
            rel = (g[sensor]["invK"] / tk[sensor]["invK"] - 1) * 1e6
            print(f"    imupipe {name:6s} {np.round(g[sensor]['invK'], 2)}  ({np.round(rel):} ppm vs imu_tk)")
        print(f"    Xsens factory  {XSENS_FACTORY[sensor]}")
        off = ~np.eye(3, dtype=bool)
        print(f"    T off-diagonal imu_tk        {np.round(tk[sensor]['T'][off], 5)}")
        for name, g in mine.items():
            print(f"    T off-diagonal imupipe {name:6s}{np.round(g[sensor]['T'][off], 5)}")
    print(f"  biases imupipe B: accel {np.round(timings[False][1][0].b0, 1)}, gyro "
          f"{np.round(timings[False][1][1].b0, 1)}  (imu_tk: {IMU_TK['accel']['b']}, {IMU_TK['gyro']['b']})")

    print("\n2. Control-set gravity error after each turn (same code for all: control_errors)")
    nominal = (TriadCalibration("accel", np.eye(3)), TriadCalibration("gyro", np.eye(3)))
    tk_cal = (imu_tk_calibration("accel"), imu_tk_calibration("gyro"))
    held = (np.arange(len(turns)) % args.every) == args.every - 1
    cal_rests, cal_turns, ctl_turns = split(rests, turns, args.every)
    cases = [
        (f"held-out turns: every {args.every}th turn's gyro unseen, rests shared",
         turns.subset(held), rests, turns.subset(~held)),
        ((f"strict: every {args.every}th turn and its two rests unseen "
          f"({len(cal_rests)} rests, {len(cal_turns)} turns left)"), ctl_turns, cal_rests, cal_turns),
        ("in-sample: all turns, everything fitted on all data", turns, rests, turns),
    ]
    for title, control, fit_rests, fit_turns in cases:
        print(f"   {title}; {len(control)} control turns")
        candidates = {
            "nominal (M = I, b = 0)": nominal,
            "imu_tk printed (fitted on all data)": tk_cal,
            "imupipe B (paper: bias Eq. 2.15)": calibrate(fit_rests, fit_turns, joint=False),
            "imupipe B, bias = adjacent_rests": calibrate(fit_rests, fit_turns, joint=False,
                                                          bias="adjacent_rests"),
            "imupipe joint (from B, paper)": calibrate(fit_rests, fit_turns, joint=True),
        }
        for name, (acc, gyr) in candidates.items():
            e = np.degrees(control_errors(acc, gyr, rests, control)[0])
            print(f"     {name:36s} RMS {np.sqrt(np.mean(e**2)):8.4f} deg, max {e.max():8.4f} deg")

    print("\n3. Time (segmentation + calibration, best of "
          f"{args.repeat}; reading the files {t_read:.2f} s more)")
    for joint, label in ((False, "method B"), (True, "method B + joint refinement")):
        print(f"   imupipe {label:28s} {timings[joint][0]:.2f} s = {timings[joint][0] / IMU_TK_SECONDS:.2f}x "
              f"imu_tk's {IMU_TK_SECONDS} s")
    print_processes()


if __name__ == "__main__":
    main()

"""Accuracy of the default pipeline on simulated standard sessions, against the targets.

    /work/venv/bin/python bench/default_pipeline_accuracy.py [--seeds 5]
        [--pipelines default sphere-rig] [--bias-rw ACCEL GYRO] [--out DIR]

Simulates ``--seeds`` sessions of the ``standard`` protocol (seeds 0, 1, ...) at
standard gravity (9.80665 m/s^2, what the shipped pipelines assume) with the
default consumer-MEMS model (white noise, quantisation, turn-on bias, thermal
drift over the warm-up) plus a bias random walk (``--bias-rw``, default
1e-5 m/s^2/sqrt(s) and 1e-6 rad/s/sqrt(s): about 0.04 mg and 0.2 deg/h over a
minute, a consumer part's in-run drift; ``0 0`` for none) and no omitted-physics
effects, writes each as
``.mcap`` with its truth, runs each pipeline through ``imupipe.pipeline.api.run_sessions``
(``default``: the built-in pipeline, method A + joint refinement; another name:
``pipelines/<name>.toml``, e.g. ``sphere-rig``, method A alone; or a path) and
prints, per seed and as RMS and max over seeds, the errors of
``imupipe.sim.compare`` beside the accuracy targets. "met" = every seed within
the target. The pipelines set no ``field_T``, so the magnetometer is judged by
its shape with the overall scale set aside. Files go to a temporary folder
unless ``--out`` is given.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from imupipe.errors import ImupipeError
from imupipe.models import Calibration
from imupipe.pipeline.api import run_sessions, session_ids
from imupipe.sim.api import simulate
from imupipe.sim.compare import CalibrationErrors, calibration_errors
from imupipe.sim.sensor import ImuModel, default_imu
from imupipe.sim.truth import load_truth

REPO = Path(__file__).resolve().parents[1]
G = 9.80665
# (label, unit, target, error from CalibrationErrors)
ROWS = [
    ("accel bias", "mg", 0.2, lambda e: e["accel"].bias),
    ("accel scale", "ppm", 200.0, lambda e: e["accel"].scale_ppm),
    ("accel non-orthogonality", "ppm", 200.0, lambda e: e["accel"].nonorth_ppm),
    ("gyro scale", "ppm", 300.0, lambda e: e["gyro"].scale_ppm),
    ("gyro non-orthogonality", "ppm", 300.0, lambda e: e["gyro"].nonorth_ppm),
    ("gyro-to-accel alignment", "deg", 0.02, lambda e: e.gyro_accel_align_deg),
    ("mag shape, scale aside", "%", 0.2, lambda e: e["mag"].shape_scale_aside_ppm * 1e-4),
]


def pipeline_path(name: str) -> Path | None:
    """``default`` -> None (the built-in pipeline); a name -> ``pipelines/<name>.toml``; else a path."""
    if name == "default":
        return None
    return Path(name) if name.endswith(".toml") else REPO / "pipelines" / f"{name}.toml"


def drifting_imu(seed: int, accel_rw: float, gyro_rw: float) -> ImuModel:
    """The simulator's default IMU for ``seed`` (its own draw), with a bias random walk."""
    imu = default_imu(np.random.default_rng([seed, 2]))  # the draw simulate() makes for seed
    return imu.model_copy(update={
        "accel": imu.accel.model_copy(update={"bias_rw": accel_rw}),
        "gyro": imu.gyro.model_copy(update={"bias_rw": gyro_rw}),
    })


def simulate_sessions(seeds: int, folder: Path, bias_rw: tuple[float, float]) -> list[Path]:
    return [simulate("standard", {}, seed, folder / f"standard-{seed}.mcap", quiet=True,
                     imu=drifting_imu(seed, *bias_rw), env={"gravity_m_s2": G})[0]
            for seed in range(seeds)]


def run_pipeline(name: str, sessions: list[Path], out: Path) -> list[CalibrationErrors | None]:
    """Errors per session (None where the pipeline failed on it; the failure is printed)."""
    try:
        run_sessions(sessions, pipeline_path(name), out, quiet=True)
    except ImupipeError as exc:
        print(f"  {name}: {exc}")
    errors: list[CalibrationErrors | None] = []
    for session, sid in zip(sessions, session_ids(sessions), strict=True):
        path = out / sid / "calibration.json"
        if not path.is_file():
            errors.append(None)
            continue
        estimate = Calibration.from_json(path.read_text())
        errors.append(calibration_errors(estimate, load_truth(session).calibration, g_m_s2=G))
    return errors


def print_table(name: str, errors: list[CalibrationErrors | None], seconds: float) -> None:
    ok = [e for e in errors if e is not None]
    print(f"\n{name}: {len(ok)}/{len(errors)} sessions calibrated, pipeline run {seconds:.1f} s")
    seeds = "".join(f"{f'seed {i}':>10s}" for i in range(len(errors)))
    print(f"{'quantity':26s}{'unit':>5s}{seeds}{'RMS':>10s}{'max':>10s}{'target':>8s}  met")
    for label, unit, target, get in ROWS:
        vals = [get(e) if e is not None else np.nan for e in errors]
        ran = np.array([v for v in vals if np.isfinite(v)])
        rms = float(np.sqrt(np.mean(ran**2))) if len(ran) else np.nan
        worst = float(ran.max()) if len(ran) else np.nan
        met = "yes" if len(ran) == len(errors) and worst <= target else "NO"
        cells = "".join(f"{v:10.4g}" for v in vals)
        print(f"{label:26s}{unit:>5s}{cells}{rms:10.4g}{worst:10.4g}{target:8g}  {met}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--pipelines", nargs="+", default=["default", "sphere-rig"],
                    help="'default', a name in pipelines/ or a .toml path")
    ap.add_argument("--bias-rw", type=float, nargs=2, default=[1e-5, 1e-6], metavar=("ACCEL", "GYRO"),
                    help="bias random walk, m/s^2/sqrt(s) and rad/s/sqrt(s)")
    ap.add_argument("--out", type=Path, default=None, help="keep sessions and results here")
    args = ap.parse_args()
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="imupipe-bench-") as tmp:
        folder = args.out or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        sessions = simulate_sessions(args.seeds, folder, tuple(args.bias_rw))
        t_sim = time.perf_counter() - t_start
        print(f"standard protocol, {args.seeds} seeds, g = {G} m/s^2, bias random walk "
              f"{args.bias_rw[0]:g} m/s^2/sqrt(s) and {args.bias_rw[1]:g} rad/s/sqrt(s), no effects; "
              f"simulated and written in {t_sim:.1f} s")
        for name in args.pipelines:
            t0 = time.perf_counter()
            errors = run_pipeline(name, sessions, folder / f"out-{Path(name).stem}")
            print_table(name, errors, time.perf_counter() - t0)
    print(f"\nwall time {time.perf_counter() - t_start:.1f} s")


if __name__ == "__main__":
    main()

"""Stages run by hand, as the runner would, for tests that need their intermediate tables.

``run_stage`` resolves a stage's solver and checks its outputs against their schemas;
``method_b_refine_inputs`` chains segmentation, method B's accel and gyro stages into
the inputs of ``refine_joint``; ``white_imu`` is a sensor with scale/misalignment and
bias errors and white noise only (optionally a gyro bias random walk). Seeded.
"""

from __future__ import annotations

import numpy as np

from imupipe import schemas
from imupipe.components import BoundSolver, Recording

G = 9.80665


def white_imu(seed: int, gyro_bias_rw: float = 0.0) -> dict:
    """Imu-model overrides: no k, turn-on bias, LSB or range; ``gyro_bias_rw`` rad/s/sqrt(s)."""
    rng = np.random.default_rng(seed)

    def triad(noise_sd: float, bias_rw: float = 0.0) -> dict:
        S = np.eye(3) + np.diag(rng.uniform(-0.02, 0.02, 3)) + (1 - np.eye(3)) * rng.normal(0, 0.01, (3, 3))
        return {"S": S.tolist(), "b0": rng.uniform(-0.05, 0.05, 3).tolist(), "noise_sd": noise_sd,
                "bias_rw": bias_rw}

    return {"accel": triad(0.5e-3 * G), "gyro": triad(np.radians(0.02), gyro_bias_rw)}


def run_stage(registry, name: str, inputs: dict, **params) -> dict:
    """Run registered stage ``name`` on ``inputs`` with ``params``; outputs checked."""
    stage = registry.get("stages", name)
    p = stage.params(**params)
    solver = None
    if stage.solver_kind:
        found = registry.get("solvers", p.solver)
        solver = BoundSolver(found, found.params(**p.solver_params))
    out = stage.func(inputs, p, solver)
    for port, schema_id in stage.outputs.items():
        schemas.check(out[port], schema_id, f"{name} output {port!r}")
    return out


def method_b_refine_inputs(registry, recording: Recording) -> dict:
    """The inputs of ``refine_joint`` after segmentation and method B's accel and gyro stages."""
    dev = recording.devices["imu"]
    seg = run_stage(registry, "segment_stillness", {"accel": dev["accel"], "gyro": dev["gyro"]})
    acc = run_stage(registry, "calibrate_accel", {"rests": seg["rests"]}, solver="ellipsoid_svd",
                    solver_params={"square_root": "cholesky"})
    gyr = run_stage(registry, "calibrate_gyro", {"rests": seg["rests"], "turns": seg["turns"],
                                                 "gyro": dev["gyro"], "accel": acc["calibration"]},
                    solver="gyro_integration")
    return {"rests": seg["rests"], "turns": seg["turns"], "gyro": dev["gyro"],
            "accel_calibration": acc["calibration"], "gyro_calibration": gyr["calibration"]}

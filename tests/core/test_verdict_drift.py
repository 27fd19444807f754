"""Issue 12: a session without temperature whose accelerometer drifts thermally is warned about
(the rests' calibrated gravity magnitude changes with time); a session without drift is not.

Simulated sphere-rig sessions (50 Hz, no warm-up: the die heats by ~12 degC during the
positions), their temperature stream dropped, segmented and calibrated by the real stages."""

from __future__ import annotations

import pytest
from stage_chain import run_stage

import imupipe.solvers
import imupipe.stages
from imupipe.models import Calibration
from imupipe.plugins import make_registry
from imupipe.sim.api import simulate_recording
from imupipe.verdict import judge

SCALE_PPM_PER_C = [500.0, 500.0, 500.0]  # 12 degC of self-heating: ~6000 ppm (the 6200)


@pytest.fixture(scope="module")
def registry():
    return make_registry([imupipe.stages, imupipe.solvers], entry_points_too=False)


def verdict_without_temperature(registry, effects: dict, thermal: dict, seed: int) -> dict:
    rec, _ = simulate_recording("sphere_rig", effects, seed=seed,
                                imu={"rate_hz": 50, "thermal": thermal}, warmup_s=0, n_positions=30,
                                n_turns=14, rest_s=2, reference_rest_s=2, max_turn_deg=30)
    dev = rec.devices["imu"]  # its temperature stream is not used: as if never logged
    seg = run_stage(registry, "segment_stillness", {"accel": dev["accel"], "gyro": dev["gyro"]},
                    min_rests=9)
    acc = run_stage(registry, "calibrate_accel", {"rests": seg["rests"]}, solver="ellipsoid_cholesky")
    doc = Calibration.from_tables(acc["calibration"]).to_dict()
    return judge(doc, {"rests.rests": seg["rests"]})


def drift(v: dict) -> dict:
    (check,) = [c for c in v["checks"] if c["check"] == "drift"]
    return check


def test_thermal_scale_drift_without_temperature_warns(registry):
    v = verdict_without_temperature(registry, {"accel_scale_temperature": {"ppm_per_C": SCALE_PPM_PER_C}},
                                    {"tau_s": 200.0}, seed=0)
    check = drift(v)
    assert check["status"] == "warn" and v["status"] in ("warn", "fail")
    assert "without a temperature stream" in check["detail"]
    assert "no static calibration explains" in check["detail"]
    assert any(r.startswith("warn: accel drift") for r in v["reasons"])


def test_no_drift_without_temperature_does_not_warn(registry):
    v = verdict_without_temperature(registry, {}, {"self_heating_C": 0.0}, seed=0)
    assert drift(v)["status"] == "pass", drift(v)["detail"]
    assert not any("drift" in r for r in v["reasons"])


"""bench/diagnosis.py's accounting: intervals, naming (traps), and the summary's verdicts."""

from __future__ import annotations

import numpy as np
from bench_scripts import BENCH, load_bench


def _bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))  # it imports residual_nulls from beside it
    return load_bench("diagnosis")


def _run(kind, sizes, findings, factor=None, candidates=(), not_identifiable=(), **judged):
    effects = {e: {"size": a, "named": False, "unresolved": False} | judged for e, a in sizes.items()}
    return {"kind": kind, "sizes": sizes, "factor": factor, "findings": list(findings),
            "candidates": list(candidates), "effects": effects, "not_identifiable": list(not_identifiable)}


def test_interval_is_estimate_plus_minus_1_96_sd(monkeypatch):
    b = _bench(monkeypatch)
    assert b.covered([1.0, 1.0], [0.5, 0.5], [1.97, 2.0]) == [True, False]


def test_trap_right_when_unknown_names_it_and_a_rival(monkeypatch):
    b = _bench(monkeypatch)
    lag = {"effect": "unknown", "sensor": "gyro", "parameters": {"candidates": ["warmup_transient", "thermal_lag"]}}
    assert b.judged("thermal_lag", 120.0, [lag], np.eye(3))["unresolved"]
    assert not b.judged("lever_arm", 1e-3, [lag], np.eye(3))["unresolved"]
    wrong_sensor = {"effect": "bias_temperature_nonlinear", "sensor": "accel", "parameters": {}}
    assert not b.judged("bias_temperature_nonlinear", 1e-6, [wrong_sensor], np.eye(3))["named"]


def test_summary_counts_each_criterion_over_its_runs(monkeypatch):
    b = _bench(monkeypatch)
    runs = [_run("null", {}, []), _run("null", {}, ["unknown"]),
            _run("effect", {"lever_arm": 1.0}, ["lever_arm"], 2.0, named=True, covered=[True, True, False],
                 heldout_ratio=0.5, heldout_chi2_n=None),
            _run("effect", {"lever_arm": 1.0}, ["accel_nonlinearity"], 5.0),
            _run("trap", {"thermal_lag": 120.0}, ["unknown"], 5.0, ["warmup_transient", "thermal_lag"],
                 unresolved=True),
            _run("absorbed", {"gyro_scale_temperature": 300.0}, [], not_identifiable=["gyro_scale_temperature"])]
    s = b.summary(runs)
    assert s["nulls: family-wise false discoveries"][0].startswith("1/2 50%")
    assert s["nulls: family-wise false discoveries"][2] == "MISS"
    assert s["nulls: share of sessions"][0].startswith("2/6 ")
    assert s["power at 2x MDE"][0].startswith("1/1 ") and s["power at 5x MDE"][0].startswith("2/2 ")
    assert s["naming accuracy"][0].startswith("1/2 ")
    assert s["naming accuracy, traps"][0].startswith("1/1 ") and s["naming accuracy, traps"][2] == "PASS"
    assert s["95 % interval coverage"][0].startswith("2/3 ")
    assert s["absorbed: discoveries"][0].startswith("0/1 ") and s["absorbed: discoveries"][2] == "PASS"
    assert s["absorbed: listed not_identifiable"][2] == "PASS"


def test_calibration_frame_is_the_rotation_between_the_truth_and_the_calibration(monkeypatch):
    b = _bench(monkeypatch)
    S = np.array([[0.97, -0.016, -0.01], [-0.023, 0.99, 0.002], [-0.013, 0.007, 1.006]])
    c, s = np.cos(0.019), np.sin(0.019)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    M = R @ np.linalg.inv(S)
    frame = b.calibration_frame({"imu": {"accel": {"S": S.tolist()}}}, {"accel": {"M": M.tolist()}})
    np.testing.assert_allclose(frame, R, atol=1e-12)

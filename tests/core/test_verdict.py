"""imupipe.verdict: each check on hand-made calibration documents and tables (no pipeline)."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pytest

from imupipe import schemas
from imupipe.report.exporter import verdict_section
from imupipe.verdict import chi2_status, fit_checks, judge, strict_failure, verdict_lines


def triad(M=None, b0=(0.0, 0.0, 0.0), sigma=True, **extra) -> dict:
    M = np.eye(3) if M is None else np.asarray(M, float)
    d = {"M": M.tolist(), "b0": list(b0), "k": [0.0] * 3, **extra}
    if sigma:
        d["sigma_M"] = (np.full((3, 3), 1e-5)).tolist()
        d["sigma_b0"] = [1e-4] * 3
    return d


def doc(accel=None, gyro=None, blocks=None) -> dict:
    d = {"session": "s.csv", "accel": accel or triad(), "gyro": gyro or triad(b0=(0.01, 0, 0))}
    if blocks is not None:
        d["accel"]["joint"] = d["gyro"]["joint"] = {"blocks": blocks}
    return d


def reasons(v: dict) -> str:
    return " | ".join(v["reasons"])


def test_a_sound_calibration_passes_with_every_check_listed():
    v = judge(doc(blocks={"accel_rest": {"chi2": 105.0, "dof": 100.0, "chi2_per_dof": 1.05}}),
              facts={"accel": {"rate_hz": 100.0}, "gyro": {"rate_hz": 100.0}})
    assert v["status"] == "pass" and v["reasons"] == []
    assert {c["check"] for c in v["checks"]} >= {"chi2", "values", "frames", "uncertainty", "rate"}
    assert verdict_lines(v)[0].startswith("verdict: pass") and not strict_failure([v])


@pytest.mark.parametrize("c, dof, expected", [
    (1.05, 100, "pass"),   # within 1 +- sqrt(2/100) * 5
    (1.9, 100, "pass"),    # beyond the spread but residuals only 1.4x the noise
    (3.0, 1000, "warn"),   # far beyond its spread and above 2
    (1000.0, 300, "warn"),  # a real hand-held recording's per-sample turn block: understated sigma
    (0.5, 10000, "warn"),  # the noise model overstates the noise
    (1.8e5, 200, "fail"),  # swapped axes (issue 12): residuals hundreds of times the noise
    (2e4, 50, "fail"),
    (float("nan"), 10, "fail"),
])
def test_chi2_per_dof_is_judged_against_its_spread(c, dof, expected):
    assert chi2_status(c, dof) == expected


def test_huge_turn_chi2_fails_and_strict_counts_it():
    v = judge(doc(blocks={"turn": {"chi2": 1.8e5 * 60, "dof": 60.0, "chi2_per_dof": 1.8e5}}))
    assert v["status"] == "fail" and "turn: chi2/dof 1.8e+05" in reasons(v)
    assert strict_failure([v]) and verdict_lines(v)[1].startswith("  fail:")


def test_without_the_residual_map_the_verdict_and_report_do_not_point_to_it():
    """calibrate.toml has the joint fit and no map: nothing may send the reader to a map it lacks."""
    blocks = {"gyro_rest": {"chi2": 3000.0, "dof": 1000.0, "chi2_per_dof": 3.0}}
    alone = judge(doc(blocks=blocks))
    assert alone["status"] == "warn" and "see the residual map" not in reasons(alone)
    assert "the default pipeline's residual map shows where" in reasons(alone)
    assert alone["not_checked"] and "not_checked" not in judge(doc())  # said only after a joint fit
    mapped = fit_checks(doc(blocks=blocks), [{"blocks": [{"block": "gyro_rest", "chi2_per_dof": 3.0, "dof": 1000}]}])
    assert all("see the residual map" in c.detail for c in mapped)
    assert any("Not checked: every sample" in line for line in verdict_section(alone))
    assert not any("Not checked" in line for line in verdict_section(
        {"status": "warn", "checks": [c.to_dict() for c in mapped]}))
    assert not any("Not checked" in line for line in verdict_section(judge(doc())))  # no joint fit


def test_left_handed_accel_fails():
    v = judge(doc(accel=triad(np.diag([1.0, -1.0, 1.0]))))
    assert v["status"] == "fail" and "accel: det M = -1 <= 0, a left-handed calibration" in reasons(v)


def test_scale_three_times_nominal_fails_but_counts_are_not_judged_by_scale():
    v = judge(doc(gyro=triad(np.eye(3) / 3)))
    assert v["status"] == "fail" and "gyro: scale factors 3, 3, 3 x nominal" in reasons(v)
    counts = triad(np.eye(3) / 400, b0=(32768.0, 32768.0, 32768.0), raw_units="counts")
    v = judge(doc(accel=counts, gyro=triad(np.eye(3) / 400, raw_units="counts")))
    assert v["status"] == "pass", reasons(v)


def test_implausible_bias_warns_then_fails():
    assert judge(doc(accel=triad(b0=(2.0, 0, 0))))["status"] == "warn"
    v = judge(doc(gyro=triad(b0=(0, 2.0, 0))))  # 115 deg/s: deg/s data or a broken gyro
    assert v["status"] == "fail" and "gyro: largest bias 2 rad/s" in reasons(v)


def test_gyro_turned_half_a_turn_from_the_accelerometer_fails():
    """An accelerometer axis sign-flipped: the gyro absorbs it as a proper half turn (det > 0)."""
    v = judge(doc(gyro=triad(np.diag([-1.0, 1.0, -1.0]))))
    assert v["status"] == "fail" and "gyro axes turned 180 deg from the accelerometer's" in reasons(v)
    c, s = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
    one_degree = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    assert judge(doc(gyro=triad(one_degree)))["status"] == "pass"


def test_missing_or_large_uncertainties():
    v = judge(doc(accel=triad(sigma=False)))
    assert v["status"] == "pass"
    big = triad()
    big["sigma_M"] = (np.full((3, 3), 0.05)).tolist()
    v = judge(doc(gyro=big))
    assert v["status"] == "warn" and "gyro: 1-sigma scale 5e+04 ppm" in reasons(v)


def rests_table(directions: np.ndarray) -> pa.Table:
    n = len(directions)
    return schemas.stamp(pa.table({
        "index": np.arange(n), "t_start_ns": np.arange(n) * 10**10, "t_end_ns": np.arange(n) * 10**10 + 5,
        "t_start_s": np.arange(n) * 10.0, "t_end_s": np.arange(n) * 10.0 + 5, "count": np.full(n, 500),
        "temperature": np.full(n, 25.0),
        "accel_mean": pa.array(list(9.81 * directions), type=pa.list_(pa.float64(), 3)),
        "accel_cov": pa.array([np.eye(3).ravel() * 1e-4] * n, type=pa.list_(pa.float64(), 9)),
        "accel_count": np.full(n, 500), "gyro_mean": pa.array([np.zeros(3)] * n, type=pa.list_(pa.float64(), 3)),
        "gyro_cov": pa.array([np.eye(3).ravel() * 1e-6] * n, type=pa.list_(pa.float64(), 9)),
        "gyro_count": np.full(n, 500)}), "rests")


def test_coverage_of_the_sphere():
    six = np.vstack([np.eye(3), -np.eye(3)])
    assert judge(doc(), {"r": rests_table(six)})["status"] == "pass"
    rng = np.random.default_rng(0)
    upper = rng.normal(size=(30, 3))
    upper[:, 2] = np.abs(upper[:, 2]) + 1.5  # every rest with gravity near sensor +z
    v = judge(doc(), {"r": rests_table(upper / np.linalg.norm(upper, axis=1, keepdims=True))})
    assert v["status"] == "warn" and "of sensor -z at best" in reasons(v)


def test_rate_and_events():
    v = judge(doc(), facts={"accel": {"rate_hz": 5.0}, "gyro": {"rate_hz": 30.0}})
    assert v["status"] == "fail" and "accel: 5 Hz" in v["reasons"][0] and "gyro: 30 Hz" in reasons(v)
    events = schemas.stamp(pa.table({"kind": ["gap", "splice"], "sensor": ["all", "accel"],
                                     "t_start_s": [1.0, 5.0], "t_end_s": [3.7, 5.01],
                                     "detail": ["2.7 s without samples", "gravity jumps 90 deg"]}), "events")
    events = events.replace_schema_metadata({**events.schema.metadata, b"imupipe.turns_left_out": b"2",
                                             b"imupipe.turns": b"40"})
    v = judge(doc(), {"e": events})
    assert v["status"] == "fail" and v["reasons"][0].startswith("fail: 1 splice in the recording")
    assert "warn: 1 gap in the recording; first: 2.7 s without samples" in v["reasons"]
    assert "warn: 2 of 40 turns left out of the fits: they hold a gap, shock or splice" in v["reasons"]
    only_gap = events.filter(pa.array([True, False]))
    assert judge(doc(), {"e": only_gap})["status"] == "warn"


def validation_table(n_inf: int, n_ok: int, before: float, after: float) -> pa.Table:
    summary = {"n_turns": n_inf, "n_informative": n_inf, "n_accepted": n_ok, "tolerance_deg": 0.1,
               "angle_error_rms_before_deg": before, "angle_error_rms_after_deg": after}
    return pa.table({"index": np.arange(1)}, metadata={schemas.SCHEMA_KEY: b"validation",
                                                        "imupipe.summary": json.dumps(summary)})


@pytest.mark.parametrize("n_ok, before, after, expected, n_inf", [
    (32, 1.5, 0.01, "pass", 32), (25, 1.5, 0.05, "warn", 32), (32, 1.5, 0.2, "warn", 32),
    (0, 1.5, 0.8, "fail", 32), (32, 0.05, 0.06, "fail", 32), (0, 4.1, 0.13, "warn", 1),
])
def test_turn_validation_against_tolerance(n_ok, before, after, expected, n_inf):
    v = judge(doc(), {"v": validation_table(n_inf, n_ok, before, after)})
    assert v["status"] == expected, reasons(v)


def test_turns_left_out_for_saturation_warn():
    d = doc(blocks={})
    d["gyro"]["joint"]["turns_saturated"] = 3  # the one joint fit both triads carry
    v = judge(d)
    assert v["status"] == "warn" and "3 turns left out of the joint fit" in reasons(v)


def test_mag_field_in_microtesla_under_tesla_fails():
    d = doc()
    d["mag"] = triad(field_T=49.9, sigma=False)  # the ellipsoid radius of data in uT
    v = judge(d)
    assert v["status"] == "fail" and "mag: field 49.9 T" in reasons(v)
    d["mag"] = triad(field_T=49.9e-6, sigma=False)
    assert judge(d)["status"] == "pass"

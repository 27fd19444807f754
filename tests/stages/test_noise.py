"""The estimate_noise stage against the simulator's truth: noise density and random walk from a
static recording, effective sample sizes of rests, and `imupipe run --pipeline noise.toml`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from imupipe import allan, schemas
from imupipe.cli import main
from imupipe.errors import SolverError
from imupipe.sim.api import simulate, simulate_recording
from imupipe.stages import noise, segment

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"
# 600 s at 100 Hz, 4 seeds x 3 axes (measured): N/N_true 0.991-1.007, K/K_true 0.38-1.20 per axis
NOISE_DENSITY_TOL = 0.03      # relative, per axis
RANDOM_WALK_RANGE = (0.6, 1.4)  # mean over the three axes of K/K_true
K_GYRO, K_ACCEL = 1e-5, 1e-4    # rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz)
WALKS = {"bias_random_walk": {"sigma": [K_GYRO] * 3, "sensor": "gyro"},
         "bias_random_walk:accel": {"sigma": [K_ACCEL] * 3, "sensor": "accel"}}


def true_density(truth, sensor: str) -> float:
    """White noise density of the simulated triad: per-sample sigma and LSB rounding, over sqrt(rate)."""
    imu = truth.data["imu"]
    return float(np.sqrt(imu[sensor]["noise_sd"] ** 2 + imu[sensor]["quantum"] ** 2 / 12) / np.sqrt(imu["rate_hz"]))


def run_noise(d, **kw):
    seg = segment.STAGE.func(d, segment.SegmentParams(), None)
    return seg, noise.STAGE.func({**d, "rests": seg["rests"]}, noise.NoiseParams(**kw), None)


@pytest.fixture(scope="module")
def static_walk():
    rec, truth = simulate_recording("warmup", WALKS, 2, duration_s=600, start_C=42.0)  # powered equilibrium
    return run_noise(dict(rec.device("imu"))), truth


def test_static_recording_gives_noise_density_and_random_walk(static_walk):
    (seg, out), truth = static_walk
    assert seg["rests"].num_rows == 1
    for t, sid in ((out["noise"], "noise"), (out["allan"], "allan"), (out["rest_noise"], "rest_noise")):
        schemas.check(t, sid)
    rows = out["noise"].to_pylist()
    for sensor, k_true in (("accel", K_ACCEL), ("gyro", K_GYRO), ("mag", 0.0)):
        r = [x for x in rows if x["sensor"] == sensor]
        assert [x["axis"] for x in r] == ["x", "y", "z"] and all(x["rate_hz"] == pytest.approx(100) for x in r)
        n_true = true_density(truth, sensor)
        for x in r:
            assert abs(x["noise_density"] / n_true - 1) < NOISE_DENSITY_TOL, (sensor, x)
        if k_true:
            ratio = np.mean([x["random_walk"] for x in r]) / k_true
            assert RANDOM_WALK_RANGE[0] < ratio < RANDOM_WALK_RANGE[1], (sensor, ratio)
    doc = json.loads(out["noise"].schema.metadata[b"imupipe.noise"])
    assert doc["kalibr"]["update_rate"] == pytest.approx(100)
    assert doc["kalibr"]["gyroscope_noise_density"] == max(x["noise_density"] for x in rows if x["sensor"] == "gyro")


def test_no_walk_fits_no_walk():
    rec, truth = simulate_recording("warmup", None, 4, duration_s=300, start_C=42.0)
    _, out = run_noise(dict(rec.device("imu")))
    for x in out["noise"].to_pylist():
        if x["sensor"] == "gyro":
            # a walk this small would add under 10 % to the Allan deviation at the longest tau
            t = x["tau_max_s"]
            assert x["random_walk"] * np.sqrt(t / 3) < 0.5 * x["noise_density"] / np.sqrt(t)


def test_effective_sample_size_white_and_walking():
    kw = dict(warmup_s=120, n_positions=20, rest_s=5.0)
    medians = {}
    for name, effects in (("white", None), ("walk", {"bias_random_walk": {"sigma": [1e-4] * 3, "sensor": "gyro"}})):
        rec, _ = simulate_recording("sphere_rig_one_stage", effects, 5, **kw)
        _, out = run_noise(dict(rec.device("imu")), min_rest_s=60.0)
        t = out["rest_noise"].to_pylist()
        short = [r for r in t if r["sensor"] == "gyro" and 3 < r["duration_s"] < 8]
        medians[name] = np.median([np.mean(r["n_eff"]) / r["count"] for r in short])
    assert 0.85 < medians["white"] <= 1.0    # white noise: the mean is worth every sample (0.95 measured)
    assert medians["walk"] < 0.3             # a walking bias: far fewer


def test_allan_fit_recovers_synthetic_terms():
    rng = np.random.default_rng(0)
    rate, n = 100.0, 200_000
    N, K = 1e-3, 1e-4
    x = N * np.sqrt(rate) * rng.standard_normal(n) + np.cumsum(K / np.sqrt(rate) * rng.standard_normal(n))
    fit = allan.fit_curve(allan.allan_curve([x], rate))
    assert abs(fit.coef["noise_density"] / N - 1) < 0.03
    assert 0.6 < fit.coef["random_walk"] / K < 1.4


def test_no_long_rest_is_an_error_naming_the_param():
    rec, _ = simulate_recording("gimbal", None, 0, rest_s=2.0, n_rotations=3, grid_deg=90.0)
    d = dict(rec.device("imu"))
    seg = segment.STAGE.func(d, segment.SegmentParams(), None)
    with pytest.raises(SolverError, match="lower noise.min_rest_s"):
        noise.STAGE.func({**d, "rests": seg["rests"]}, noise.NoiseParams(min_rest_s=30.0), None)


def test_imupipe_run_noise_pipeline_on_a_static_recording(tmp_path):
    path = tmp_path / "static.mcap"
    simulate("warmup", {}, 7, path, quiet=True, params={"duration_s": 120, "start_C": 42.0})
    out = tmp_path / "out"
    assert main(["run", str(path), "--pipeline", str(PIPELINES / "noise.toml"), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "static" / "noise.json").read_text())
    truth = json.loads(path.with_name(path.name + ".truth.json").read_text())
    assert doc["session"].endswith("static.mcap")
    assert doc["gyro"]["rate_hz"] == pytest.approx(100)
    assert set(doc["kalibr"]) >= {"accelerometer_noise_density", "accelerometer_random_walk",
                                  "gyroscope_noise_density", "gyroscope_random_walk", "update_rate"}
    imu = truth["imu"]
    n_true = np.sqrt(imu["gyro"]["noise_sd"] ** 2 + imu["gyro"]["quantum"] ** 2 / 12) / 10
    assert abs(doc["kalibr"]["gyroscope_noise_density"] / n_true - 1) < NOISE_DENSITY_TOL
    assert not (out / "static" / "calibration.json").exists()
    report = (out / "static" / "report.md").read_text()
    assert "Allan deviation" in report and (out / "static" / "figures" / "allan_deviation.png").is_file()
    assert (out / "static" / "figures" / "rests_in_time.png").is_file()

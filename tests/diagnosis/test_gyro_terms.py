"""The gyro's motion terms and the thermal lag in the diagnosis, on a short simulated gimbal session
(consumer-MEMS noise, a 0.125 degC temperature read-out, a warm-up from power-on): each, concealed
at 5x its minimum detectable size along a fixed direction, is named and fitted within three
standard errors; the warm-up transient and the thermal lag are not mistaken for each other; a
clipping gyro is reported as saturation events, not as physics; the null is quiet."""

from __future__ import annotations

import numpy as np
import pytest
from forward_synth import G, rests_from_truth

from imupipe.diagnosis.diagnose import diagnose
from imupipe.diagnosis.evaluate import evaluate
from imupipe.diagnosis.events import detect
from imupipe.diagnosis.select import LAG_MIN_S, NONCENTRALITY_80, UNTESTED
from imupipe.sim.api import known_effects, simulate_arrays
from imupipe.sim.sensor import default_imu
from imupipe.temperature import smoothed

SEED = 3
FACTOR = 5.0
UNIT = np.array([1.0, -1.0, 1.0]) / np.sqrt(3)
SESSION = dict(grid_deg=90.0, rest_s=2.0, step_s=1.5, n_rotations=60, rotation_s=2.0)
NEW = ("gyro_scale_temperature", "gyro_scale_asymmetry", "thermal_lag")
PARAMETER = {"gyro_scale_temperature": "ppm_per_C", "gyro_scale_asymmetry": "eps", "warmup_transient": "amp"}


def _diagnosis(effects: dict) -> tuple[dict, object]:
    imu = default_imu(np.random.default_rng([SEED, 2]))
    imu = imu.model_copy(update={"thermal": imu.thermal.model_copy(
        update={"readout_quantum_C": 0.125, "tau_s": 300.0, "self_heating_C": 20.0})})
    out, truth = simulate_arrays("gimbal", effects, SEED, imu=imu, env={"gravity_m_s2": G}, **SESSION)
    rests, turns = rests_from_truth(out, truth, imu.accel.noise_sd, imu.gyro.noise_sd)
    streams = {s: (out.t, out.raw[s]) for s in ("accel", "gyro")}
    cal = truth.calibration
    ev = evaluate(streams, rests, turns, cal["accel"], cal["gyro"], G,
                  temperature=(out.t, smoothed(out.t, out.temperature)), events=detect(streams))
    return diagnose(ev, None, known_effects()), ev


@pytest.fixture(scope="module")
def null() -> dict:
    return _diagnosis({})[0]


def _tested(doc: dict, effect: str, tau_s: float | None = None) -> dict:
    return next(t for t in doc["tested"] if t["effect"] == effect and t.get("tau_s") == tau_s)


def _size_and_error(null: dict, effect: str, tau_s: float | None = None) -> tuple[float, float, np.ndarray]:
    """``FACTOR`` times the minimum detectable size along the bench's direction, the standard error
    of the fit along it (the expected information of the null session) and the direction."""
    info = np.asarray(_tested(null, effect, tau_s)["information"])
    d = UNIT if len(info) == 3 else np.ones(1)
    return FACTOR * np.sqrt(NONCENTRALITY_80 / (d @ info @ d)), float(np.sqrt(d @ np.linalg.inv(info) @ d)), d


def test_the_null_is_quiet_and_the_new_terms_are_tested(null):
    assert null["findings"] == [] and null["not_confirmed"] == []
    assert not set(NEW) & set(UNTESTED)
    for effect in ("gyro_scale_temperature", "gyro_scale_asymmetry"):
        assert _tested(null, effect)["visible_fraction"] >= 0.05
    # without a lag the read-out's rate in a first-order warm-up is affine in its temperature: k
    # and the bias make it (memo E13); a lag shows as its own start-up, tested when it is there
    (lag,) = [n for n in null["not_identifiable"] if n["effect"] == "thermal_lag"]
    assert "cool-down" in lag["reveal_with"]
    assert [u["effect"] for u in null["untested"] if u["effect"].startswith("gyro")] == ["gyro_saturation"]


@pytest.mark.parametrize("effect", ["gyro_scale_temperature", "gyro_scale_asymmetry"])
def test_a_concealed_gyro_scale_term_is_named_fitted_and_proved_on_held_out_motions(null, effect):
    a, se, d = _size_and_error(null, effect)
    doc, _ = _diagnosis({effect: {PARAMETER[effect]: list(a * d)}})
    assert [f["effect"] for f in doc["findings"]] == [effect], doc["findings"]
    f = doc["findings"][0]
    assert (f["sensor"], f["regime"]) == ("gyro", "motion")
    assert abs(np.asarray(f["parameters"][PARAMETER[effect]]) @ d - a) < 3 * se
    assert f["heldout_rms_after"] < f["heldout_rms_before"] and f["heldout_z"] > 1.645


def test_a_thermal_lag_is_named_not_a_warm_up_and_its_time_constant_fitted():
    # its signature is the read-out's start-up after power-on, whose length is the lag itself:
    # named from the smoother's scale up (5x the null's MDE is below it on this session)
    tau = 4 * LAG_MIN_S
    doc, ev = _diagnosis({"thermal_lag": {"tau_s": tau}})
    assert [f["effect"] for f in doc["findings"]] == ["thermal_lag"], doc["findings"]
    assert doc["findings"][0]["sensor"] == "temperature"  # effects.md: the read-out lags
    # the k the lag biased is refitted with the term; what is left is second order in tau / tau_T
    assert abs(doc["findings"][0]["parameters"]["tau_s"] - tau) < 0.1 * tau


def test_a_warm_up_transient_is_named_not_a_thermal_lag_and_its_time_constant_fitted(null):
    # a time constant between the selection's grid points (30 and 120 s): profiled, not the grid's
    tau = 50.0
    a, _, d = _size_and_error(null, "warmup_transient", 30.0)
    doc, _ = _diagnosis({"warmup_transient": {"amp": list(a * d), "tau_s": tau, "sensor": "gyro"}})
    assert [f["effect"] for f in doc["findings"]] == ["warmup_transient"], doc["findings"]
    assert not [f for f in doc["not_confirmed"] if f["effect"] == "thermal_lag"]
    p, sd = doc["findings"][0]["parameters"], doc["findings"][0]["parameters_sd"]
    assert 0 < sd["tau_s"] < 0.5 * tau and abs(p["tau_s"] - tau) < 3 * sd["tau_s"]
    amp, amp_sd = np.asarray(p["amp"]), np.asarray(sd["amp"])
    assert np.all(np.abs(amp - a * d) < 3 * amp_sd)


def test_a_clipping_gyro_is_reported_as_saturation_not_as_physics(null):
    doc, ev = _diagnosis({"gyro_saturation": {"limit_rad_s": 1.2}})
    clipped = [e for e in ev.events if e.kind == "saturation"]
    assert clipped and all(e.sensor == "gyro" for e in clipped)
    assert 0 < len(ev.turn_index) < ev.lin.model.n - 1  # the clipped motions are left out (n - 1 in all)
    assert doc["findings"] == [], doc["findings"]

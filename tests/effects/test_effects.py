"""Every effect leaves its documented signature, with the parameters and signs of effects.md.

Most tests simulate an ideal IMU (S = I, no bias, noise or quantisation) with and
without the effect, so the difference is the effect's term exactly.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from imupipe.components import Effect, Params
from imupipe.effects._base import EffectBase
from imupipe.hookspecs import hookimpl
from imupipe.errors import ConfigError
from imupipe.sim.api import known_effects, recording_arrays, simulate_recording
from imupipe.sim.environment import EARTH_RATE_RAD_S, Environment
from imupipe.sim.sensor import ImuModel, ThermalModel

IDEAL = ImuModel(thermal=ThermalModel(readout_quantum_C=0.0))
CATALOGUE = Path("/work/shared/spec/effects.md")


def run(protocol, effects=None, imu=IDEAL, seed=0, **kw):
    rec, truth = simulate_recording(protocol, effects or {}, seed, imu=imu, **kw)
    return recording_arrays(rec), truth


def rest_mask(x, truth, margin_s=0.05):
    m = np.zeros(len(x["t"]), bool)
    for a, b in truth.rests:
        m |= (x["t"] >= a + margin_s) & (x["t"] < b - margin_s)
    return m


def test_catalogue_is_complete():
    names = set(re.findall(r"^\| `(\w+)` \|", CATALOGUE.read_text(), re.MULTILINE)) - {"unknown"}
    assert names == set(known_effects())


class _OffsetParams(Params):
    offset: list[float]


class _GyroOffset(EffectBase):
    identifier = "test_gyro_offset"
    sensors = ("gyro",)
    stage = "bias"
    params = _OffsetParams
    physics = "a constant added to the gyro (a third-party effect)."

    def _apply(self, streams, ctx, p, rng) -> None:
        streams["gyro"] = streams["gyro"] + np.asarray(p.offset)


class _Plugin:
    @hookimpl
    def imupipe_register_effects(self, register):
        register(_GyroOffset())


def test_a_plugin_effect_is_simulated_through_the_same_hook():
    assert "test_gyro_offset" in known_effects([_Plugin()]) and "test_gyro_offset" not in known_effects()
    offset = [1e-3, -2e-3, 3e-3]
    x0, _ = run("gimbal", n_rotations=3, grid_deg=90.0)
    x1, truth = run("gimbal", {"test_gyro_offset": {"offset": offset}}, n_rotations=3, grid_deg=90.0,
                    plugins=[_Plugin()])
    np.testing.assert_allclose(x1["gyro"] - x0["gyro"], np.broadcast_to(offset, x0["gyro"].shape), atol=1e-15)
    assert list(truth.effects) == ["test_gyro_offset"]
    with pytest.raises(ConfigError, match="unknown effect 'test_gyro_offset'"):
        run("gimbal", {"test_gyro_offset": {"offset": offset}}, n_rotations=3, grid_deg=90.0)


@pytest.mark.parametrize("name", sorted(known_effects()))
def test_effect_contract(name):
    effect = known_effects()[name]
    assert isinstance(effect, Effect)
    assert effect.identifier == name
    assert effect.stage in ("timing", "temperature", "input", "sensed", "bias", "output")
    with pytest.raises(ConfigError, match=f"effect {name}: .*expected parameters"):
        effect.validate({"no_such_parameter": 1})
    assert effect.__doc__ or type(effect).__module__


def test_gyro_g_sensitivity_follows_gravity_in_body_axes():
    G = np.array([[1e-3, 2e-4, 0], [0, -5e-4, 3e-4], [1e-4, 0, 8e-4]])
    x0, truth = run("ferraris")
    x1, _ = run("ferraris", {"gyro_g_sensitivity": {"G": G.tolist()}})
    m = rest_mask(x0, truth)
    np.testing.assert_allclose((x1["gyro"] - x0["gyro"])[m], x0["accel"][m] @ G.T, atol=1e-15)
    # static means differ between poses in proportion to gravity in body axes
    assert np.ptp((x1["gyro"] - x0["gyro"])[m][:, 0]) > 0.01


def test_earth_rotation_vertical_component_is_omega_sin_latitude():
    x, truth = run("ferraris", {"earth_rotation": {"latitude_deg": 48.1}})
    m = rest_mask(x, truth)
    w, f = x["gyro"][m], x["accel"][m]
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), EARTH_RATE_RAD_S, rtol=1e-12)
    up = f / np.linalg.norm(f, axis=1, keepdims=True)
    np.testing.assert_allclose(np.sum(w * up, axis=1), EARTH_RATE_RAD_S * np.sin(np.radians(48.1)), rtol=1e-9)


def test_accel_scale_temperature_scales_with_die_temperature():
    ppm = np.array([100.0, -50.0, 200.0])
    x0, _ = run("warmup", duration_s=300.0)
    x1, _ = run("warmup", {"accel_scale_temperature": {"ppm_per_C": ppm.tolist()}}, duration_s=300.0)
    expected = x0["accel"] * (1 + np.outer(x0["temperature"] - 25.0, ppm * 1e-6))
    np.testing.assert_allclose(x1["accel"], expected, rtol=1e-14, atol=1e-14)


def test_gyro_scale_temperature_scales_rates():
    ppm = np.array([300.0, 300.0, -300.0])
    x0, _ = run("turntable")
    x1, _ = run("turntable", {"gyro_scale_temperature": {"ppm_per_C": ppm.tolist()}})
    expected = x0["gyro"] * (1 + np.outer(x0["temperature"] - 25.0, ppm * 1e-6))
    np.testing.assert_allclose(x1["gyro"], expected, rtol=1e-14, atol=1e-17)


def test_accel_nonlinearity_adds_k2_f_squared():
    k2 = np.array([1e-4, -2e-4, 5e-5])
    x0, _ = run("ferraris")
    x1, _ = run("ferraris", {"accel_nonlinearity": {"k2": k2.tolist()}})
    np.testing.assert_allclose(x1["accel"] - x0["accel"], k2 * x0["accel"] ** 2, atol=1e-13)


def test_gyro_scale_asymmetry_differs_by_sense():
    eps = np.array([0.01, 0.02, -0.005])
    x0, _ = run("turntable")
    x1, _ = run("turntable", {"gyro_scale_asymmetry": {"eps": eps.tolist()}})
    w0, w1 = x0["gyro"], x1["gyro"]
    big = np.abs(w0) > 0.1
    ratio = w1[big] / w0[big]
    sign = np.sign(w0[big])
    np.testing.assert_allclose(ratio, 1 + (np.broadcast_to(eps, w0.shape)[big] * sign), rtol=1e-12)


def test_time_offset_changes_nothing_at_rest_and_delays_motion():
    x0, truth = run("gimbal", n_rotations=5, grid_deg=60.0)
    x1, _ = run("gimbal", {"accel_gyro_time_offset": {"dt_s": 0.01}}, n_rotations=5, grid_deg=60.0)
    m = rest_mask(x0, truth)
    np.testing.assert_array_equal(x1["accel"][m], x0["accel"][m])
    # one sample period late: sample k shows what sample k-1 showed
    np.testing.assert_allclose(x1["accel"][1:], x0["accel"][:-1], atol=1e-12)
    np.testing.assert_array_equal(x1["gyro"], x0["gyro"])
    assert np.max(np.abs(x1["accel"] - x0["accel"])) > 0.05


def test_lever_arm_adds_tangential_and_centripetal_terms():
    r = np.array([0.02, -0.03, 0.05])
    x0, truth = run("gimbal", n_rotations=5, grid_deg=60.0)
    x1, _ = run("gimbal", {"lever_arm": {"r_m": r.tolist()}}, n_rotations=5, grid_deg=60.0)
    from imupipe.sim.protocols import build, protocol_params

    traj = build("gimbal", protocol_params("gimbal", n_rotations=5, grid_deg=60.0), np.random.default_rng([0, 1])).trajectory
    kin = traj.evaluate(x0["t"])
    expected = np.cross(kin.alpha, r) + np.cross(kin.omega, np.cross(kin.omega, r))
    np.testing.assert_allclose(x1["accel"] - x0["accel"], expected, atol=1e-12)
    m = rest_mask(x0, truth)
    np.testing.assert_array_equal(x1["accel"][m], x0["accel"][m])


def test_mag_current_interference_is_a_square_wave():
    p = {"offset_T": [2e-6, -1e-6, 0.5e-6], "period_s": 2.0, "duty": 0.25, "phase_s": 0.5}
    x0, _ = run("turntable")
    x1, _ = run("turntable", {"mag_current_interference": p})
    d = x1["mag"] - x0["mag"]
    on = np.mod(x0["t"] - 0.5, 2.0) < 0.5
    np.testing.assert_allclose(d[on], np.broadcast_to(p["offset_T"], d[on].shape), atol=1e-18)
    np.testing.assert_allclose(d[~on], 0.0, atol=1e-18)
    assert abs(on.mean() - 0.25) < 0.01


def test_mag_field_gradient_sets_magnitude_per_place():
    levels = [48e-6, 53e-6]
    x, truth = run("standard", {"mag_field_gradient": {"levels_T": levels}}, warmup_s=5.0, n_positions=10)
    move = truth.segments("move")[0]
    before, after = x["t"] < move["t_start_s"], x["t"] >= move["t_end_s"]
    np.testing.assert_allclose(np.linalg.norm(x["mag"][before], axis=1), levels[0], rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(x["mag"][after], axis=1), levels[1], rtol=1e-12)


def test_thermal_lag_reported_temperature_obeys_first_order_lag():
    tau = 60.0
    x0, _ = run("warmup", duration_s=600.0)
    x1, _ = run("warmup", {"thermal_lag": {"tau_s": tau}}, duration_s=600.0)
    T_die, T_rep = x0["temperature"], x1["temperature"]
    assert np.all(T_rep[1:] < T_die[1:])  # lags behind while heating
    dt = np.gradient(T_rep, x1["t"])
    residual = tau * dt - (T_die - T_rep)
    assert np.max(np.abs(residual[10:-10])) < 1e-5 * np.max(T_die - T_rep)
    # the accelerometer's bias follows the die, not the read-out
    np.testing.assert_array_equal(x1["accel"], x0["accel"])


def test_bias_temperature_nonlinear_is_quadratic():
    k2 = [1e-6, -2e-6, 3e-6]
    x0, _ = run("warmup", duration_s=300.0)
    x1, _ = run("warmup", {"bias_temperature_nonlinear": {"k2_per_C2": k2, "sensor": "gyro"}}, duration_s=300.0)
    np.testing.assert_allclose(x1["gyro"] - x0["gyro"], np.outer((x0["temperature"] - 25) ** 2, k2), atol=1e-17)


def test_warmup_transient_restarts_at_power_on():
    amp, tau = [0.01, -0.02, 0.005], 50.0
    kw = {"duration_s": 200.0, "off_s": 100.0, "restart_s": 200.0}
    x0, truth = run("cooldown_hot_restart", **kw)
    x1, _ = run("cooldown_hot_restart", {"warmup_transient": {"amp": amp, "tau_s": tau, "sensor": "accel"}}, **kw)
    t = x0["t"]
    t_on = np.where(t < 200.0, t, t - 300.0)
    np.testing.assert_allclose(x1["accel"] - x0["accel"], np.outer(np.exp(-t_on / tau), amp), atol=1e-15)
    assert truth.data["power_windows_s"] == [[0.0, 200.0], [300.0, 500.0]]


def test_bias_random_walk_grows_as_sigma_sqrt_t():
    sigma = [1e-4, 2e-4, 4e-4]
    x0, _ = run("warmup", duration_s=400.0)
    x1, _ = run("warmup", {"bias_random_walk": {"sigma": sigma, "sensor": "gyro"}}, duration_s=400.0)
    d = x1["gyro"] - x0["gyro"]
    step = np.diff(d[::100], axis=0)  # 1-s increments
    np.testing.assert_allclose(step.std(axis=0), sigma, rtol=0.12)
    assert np.all(np.abs(d[0]) < 1e-12)


def test_gyro_saturation_clips_fast_rotations():
    x, _ = run("gimbal", {"gyro_saturation": {"limit_rad_s": 1.0}}, n_rotations=8, grid_deg=60.0)
    assert np.max(np.abs(x["gyro"])) == 1.0
    assert np.sum(np.abs(x["gyro"]) == 1.0) > 10


def test_switching_an_effect_on_leaves_other_random_numbers_alone():
    """With the default noisy IMU, a dynamic-only effect leaves every rest sample unchanged."""
    rec0, truth = simulate_recording("gimbal", {}, 9, n_rotations=4, grid_deg=90.0)
    rec1, _ = simulate_recording("gimbal", {"lever_arm": {"r_m": [0.1, 0, 0]}}, 9, n_rotations=4, grid_deg=90.0)
    x0, x1 = recording_arrays(rec0), recording_arrays(rec1)
    m = rest_mask(x0, truth)
    np.testing.assert_array_equal(x1["accel"][m], x0["accel"][m])
    np.testing.assert_array_equal(x1["gyro"], x0["gyro"])


def test_two_instances_of_one_effect_on_two_triads():
    amp = [0.01, 0.02, 0.03]
    x0, _ = run("warmup", duration_s=60.0)
    x1, truth = run("warmup", {"warmup_transient": {"amp": amp, "tau_s": 10.0, "sensor": "gyro"},
                               "warmup_transient:accel": {"amp": amp, "tau_s": 10.0, "sensor": "accel"}},
                    duration_s=60.0)
    expected = np.outer(np.exp(-x0["t"] / 10.0), amp)
    np.testing.assert_allclose(x1["gyro"] - x0["gyro"], expected, atol=1e-15)
    np.testing.assert_allclose(x1["accel"] - x0["accel"], expected, atol=1e-14)
    assert set(truth.effects) == {"warmup_transient", "warmup_transient:accel"}


def test_regressors_reproduce_the_linear_terms():
    effects = known_effects()
    G = np.arange(9.0).reshape(3, 3) * 1e-4
    r = np.array([0.02, -0.01, 0.03])
    x0, _ = run("gimbal", n_rotations=3, grid_deg=90.0)
    x1, _ = run("gimbal", {"gyro_g_sensitivity": {"G": G.tolist()}, "lever_arm": {"r_m": r.tolist()}},
                n_rotations=3, grid_deg=90.0)
    from imupipe.sim.protocols import build, protocol_params

    traj = build("gimbal", protocol_params("gimbal", n_rotations=3, grid_deg=90.0), np.random.default_rng([0, 1])).trajectory
    kin = traj.evaluate(x0["t"])
    f_centre = kin.specific_force(Environment().g)
    J = effects["gyro_g_sensitivity"].regressors({"f": f_centre})
    np.testing.assert_allclose(x1["gyro"] - x0["gyro"], J @ G.ravel(), atol=1e-15)
    J = effects["lever_arm"].regressors({"omega": kin.omega, "alpha": kin.alpha})
    np.testing.assert_allclose(x1["accel"] - x0["accel"], J @ r, atol=1e-12)

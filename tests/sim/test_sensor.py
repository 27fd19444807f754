"""The sensor model matches imupipe.models' forward model; noise, temperature and protocols are as stated."""

from __future__ import annotations

import numpy as np

from imupipe.sim.api import simulate_arrays
from imupipe.sim.protocols import build, protocol_params
from imupipe.sim.sensor import DEG, G0, ImuModel, ThermalModel, default_imu

QUIET = {"noise_sd": 0.0, "quantum": 0.0, "turn_on_sd": 0.0}


def _quiet_imu(seed: int) -> ImuModel:
    base = default_imu(np.random.default_rng(seed))
    return base.model_copy(update={
        s: base.triad(s).model_copy(update=QUIET) for s in ("accel", "gyro", "mag")
    } | {"thermal": ThermalModel(readout_quantum_C=0.0)})


def test_raw_equals_models_forward_model_of_the_truth():
    out, truth = simulate_arrays("standard", {}, 4, imu=_quiet_imu(4), warmup_s=60.0, n_positions=15)
    for s in ("accel", "gyro", "mag"):
        predicted = truth.calibration[s].predict(out.inputs[s], out.temperature)
        np.testing.assert_allclose(out.raw[s], predicted, rtol=1e-13, atol=1e-13 * np.abs(out.raw[s]).max())
        corrected = truth.calibration[s].apply(out.raw[s], out.temperature)
        np.testing.assert_allclose(corrected, out.inputs[s], atol=1e-12 * np.abs(out.inputs[s]).max())


def test_default_noise_levels_per_sample():
    out, _truth = simulate_arrays("warmup", {}, 5, duration_s=120.0)
    # difference of consecutive samples removes the slow thermal drift: std = sqrt(2) sigma
    for s, sigma in (("accel", 0.5e-3 * G0), ("gyro", 0.02 * DEG)):
        d = np.diff(out.raw[s], axis=0).std(axis=0) / np.sqrt(2)
        np.testing.assert_allclose(d, sigma, rtol=0.08)


def test_one_hour_warmup_heats_about_twenty_degrees():
    out, truth = simulate_arrays("warmup", {}, 6, imu=ImuModel())
    rise = truth.data["temperature_die_C"]["end"] - truth.data["temperature_die_C"]["start"]
    assert 19.0 < rise < 20.0  # 20 (1 - exp(-3600/600))
    tau, dT = 600.0, 20.0
    expected = 22.0 + dT * (1 - np.exp(-out.t / tau))
    np.testing.assert_allclose(out.T_die, expected, atol=1e-6)


def test_hot_restart_draws_a_new_turn_on_bias_and_cools_while_off():
    out, truth = simulate_arrays("cooldown_hot_restart", {}, 7, duration_s=600.0, off_s=300.0, restart_s=300.0)
    on = np.array(truth.data["turn_on_bias"]["gyro"])
    assert on.shape == (2, 3) and not np.allclose(on[0], on[1])
    first_after = out.T_die[out.t >= 900.0][0]
    # heated for 600 s, then unpowered for 300 s: the rise above ambient decays by exp(-300/600)
    np.testing.assert_allclose(first_after - 22.0, 20.0 * (1 - np.exp(-1.0)) * np.exp(-0.5), rtol=1e-6)


def test_sphere_rig_turns_are_small_and_steered_path_covers_the_sphere():
    cover = {}
    for path in ("steered", "walk"):
        p = protocol_params("sphere_rig_one_stage", path=path, n_positions=200, warmup_s=0.0)
        traj = build("sphere_rig_one_stage", p, np.random.default_rng(0)).trajectory
        turns = [s for _, _, s in traj.boundaries() if s.label == "turn"]
        assert max(abs(s.angle_rad) for s in turns) <= 5 * DEG + 1e-12
        rests = [(a + b) / 2 for a, b, s in traj.boundaries() if s.label == "rest"]
        up = traj.evaluate(np.array(rests)).to_body([0.0, 0.0, 1.0])
        cover[path] = np.linalg.eigvalsh(up.T @ up / len(up))[0]
    assert cover["steered"] > 0.25  # 1/3 would be perfectly uniform
    assert cover["steered"] > cover["walk"]


def test_gimbal_grid_and_control_recording():
    p = protocol_params("gimbal")
    plan = build("gimbal", p, np.random.default_rng(0))
    labels = [s.label for _, _, s in plan.trajectory.boundaries()]
    assert labels.count("gimbal_rotation") == 45
    assert labels.count("rest") == 18 * 10 + 45
    control = build("gimbal", protocol_params("gimbal", control=True), np.random.default_rng(0))
    a = [s.axis for _, _, s in plan.trajectory.boundaries() if s.label == "gimbal_rotation"]
    b = [s.axis for _, _, s in control.trajectory.boundaries() if s.label == "gimbal_rotation"]
    assert a != b


def test_reference_positions_point_the_right_axis_up():
    out, truth = simulate_arrays("sphere_rig", {}, 8, n_positions=20, n_turns=10, warmup_s=10.0)
    g = truth.data["environment"]["g_m_s2"]
    for label, axis in (("reference_y_up", 1), ("reference_x_up", 0), ("reference_z_down", 2)):
        a, b = truth.rests[truth.reference_rests[label]]
        m = (out.t >= a) & (out.t < b)
        f = out.inputs["accel"][m].mean(axis=0)
        expected = np.zeros(3)
        expected[axis] = -g if label.endswith("down") else g
        np.testing.assert_allclose(f, expected, atol=1e-9)


def test_ambient_swing_is_filtered_by_the_thermal_time_constant():
    imu = ImuModel(thermal=ThermalModel(self_heating_C=0.0, readout_quantum_C=0.0, tau_s=100.0))
    out, _ = simulate_arrays("warmup", {}, 0, imu=imu, duration_s=3000.0, swing_C=2.0, swing_period_s=600.0)
    late = out.t > 1500.0  # transients gone (15 tau)
    amplitude = (out.T_die[late].max() - out.T_die[late].min()) / 2
    w = 2 * np.pi / 600.0
    np.testing.assert_allclose(amplitude, 2.0 / np.sqrt(1 + (w * 100.0) ** 2), rtol=1e-4)


def test_bias_instability_is_a_gauss_markov_process_of_its_sd_and_correlation_time():
    from imupipe.sim.engine import gauss_markov

    t = np.arange(0.0, 40_000.0, 0.05)
    x = gauss_markov(t, 2e-5, 100.0, np.random.default_rng(0))
    assert np.allclose(x.std(axis=0), 2e-5, rtol=0.1)
    lag = int(100.0 / 0.05)
    rho = np.mean([np.corrcoef(x[:-lag, i], x[lag:, i])[0, 1] for i in range(3)])
    assert abs(rho - np.exp(-1)) < 0.05

"""The pooled system of several sessions (``diagnosis/pool.py``) on small noise-free gimbal sessions:
its layout, the one-unit check, and the held-out check by session."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from forward_synth import G, joint_model, noise_free_imu, rests_from_truth, small_gimbal

from imupipe.diagnosis.evaluate import Evaluation
from imupipe.diagnosis.linearised import fit
from imupipe.diagnosis.pool import check_one_unit, diagnose_pooled, pool, pooled_candidates, pooled_walks
from imupipe.diagnosis.select import VISIBLE_MIN, candidates, examine, rigid_walks, time_blocks
from imupipe.errors import ImupipeError
from imupipe.sim.api import known_effects, simulate_arrays
from imupipe.sim.sensor import default_imu
from imupipe.solvers.joint_ml import gyro_walk_intensity

PPM = [300.0, -200.0, 100.0]  # ppm/degC
TEMPERATURES = (5.0, 25.0, 45.0)
GYRO_RW = 1e-6  # rad/s/sqrt(s)


def _fitted(die_C: float, effects: dict | None, seed: int = 3, warming: bool = False):
    """A noise-free gimbal session of one unit with its die held at ``die_C`` (``warming``: from
    ``die_C``, heating by several degC in a minute, its k fitted), fitted."""
    imu = noise_free_imu(3)
    imu["thermal"] = {"readout_quantum_C": 0.0, "ambient_C": die_C - 20.0, "initial_C": die_C}
    if warming:
        imu["thermal"] = {"readout_quantum_C": 0.0, "ambient_C": die_C, "self_heating_C": 40.0, "tau_s": 60.0}
    out, truth = small_gimbal(seed, imu) if not effects else _with(seed, imu, effects)
    model = joint_model(out, truth, fit_k=warming)[0]
    return fit(model, max_iter=5)


def _with(seed, imu, effects):
    return simulate_arrays("gimbal", effects, seed, imu=imu, env={"gravity_m_s2": G},
                           grid_deg=60.0, rest_s=2.0, step_s=1.5, n_rotations=6, rotation_s=2.0)


def _consumer_unit(seed: int):
    """The simulator's consumer-MEMS unit (noise, quantisation, turn-on bias) with a gyro bias walk."""
    imu = default_imu(np.random.default_rng([seed, 2]))
    return imu.model_copy(update={"gyro": imu.gyro.model_copy(update={"bias_rw": GYRO_RW})})


@pytest.fixture(scope="module")
def nulls():
    return [_fitted(T, None, seed=3 + i) for i, T in enumerate(TEMPERATURES)]


def test_the_calibration_is_shared_and_the_biases_and_nuisances_are_per_session(nulls):
    a, b = nulls[:2]
    lin = pool([a, b])
    assert list(lin.globals.slices) == ["S_a", "M_g", "b_a#0", "b_g#0", "b_a#1", "b_g#1"]
    n_a = len(a.r)
    s = lin.globals.slices
    for name in ("S_a", "M_g"):  # one set of columns for both sessions' rows
        np.testing.assert_array_equal(lin.J_g[:n_a, s[name]], a.J_g[:, a.globals.slices[name]])
        np.testing.assert_array_equal(lin.J_g[n_a:, s[name]], b.J_g[:, b.globals.slices[name]])
    assert not lin.J_g[n_a:, s["b_a#0"]].any() and not lin.J_g[:n_a, s["b_g#1"]].any()
    # nuisances block-diagonal, their stages one chain after the other
    assert lin.J_l.shape == (n_a + len(b.r), a.J_l.shape[1] + b.J_l.shape[1])
    assert not lin.J_l[:n_a, a.J_l.shape[1]:].count_nonzero()
    assert list(lin.model.stages.offsets) == list(a.model.stages.offsets) + \
        list(b.model.stages.offsets[1:] + a.model.stages.offsets[-1])
    # no time block of the wild bootstrap joins two sessions
    blocks = time_blocks(lin)
    assert not set(blocks[:n_a]) & set(blocks[n_a:])
    # the residuals at the sessions' mean calibration: what the pooled step then moves
    shift = sum(a.J_g[:, a.globals.slices[name]] @ (lin.x_g[s[name]] - a.x_g[a.globals.slices[name]])
                for name in ("S_a", "M_g"))
    np.testing.assert_allclose(lin.r[:n_a] - a.r, shift, atol=1e-12)
    x = 0.5 * (a.x_g[a.globals.slices["S_a"]] + b.x_g[b.globals.slices["S_a"]])
    np.testing.assert_allclose(lin.x_g[s["S_a"]], x)
    # the pooled normal system solves (the per-session biases are determined)
    assert np.all(np.isfinite(lin.cov_g()))


def test_another_unit_is_refused_naming_its_file(nulls):
    a, b = nulls[:2]
    check_one_unit([a, b], ["a.csv", "b.csv"])
    x = b.x_g.copy()
    x[b.globals.slices["S_a"]][0] += 0.05  # a 5 % scale: another part
    other = dataclasses.replace(b, x_g=x)
    with pytest.raises(ImupipeError, match=r"^b\.csv: its accelerometer scale/misalignment differs from a\.csv's"):
        check_one_unit([a, other], ["a.csv", "b.csv"])


def test_three_null_sessions_give_no_finding(nulls):
    doc = diagnose_pooled([Evaluation(lin, np.eye(3), None) for lin in nulls], known_effects(), ["a", "b", "c"])
    assert doc["findings"] == [] and doc["sessions"] == ["a", "b", "c"]
    assert "held out by session" in doc["method"]


def test_what_one_session_sees_stays_visible_beside_a_session_that_absorbs_it(nulls):
    # at 45 degC a temperature curvature is a constant the session's bias takes: in the pooled
    # columns it would dilute the fraction the warming session shows
    warm = _fitted(25.0, None, warming=True)
    doc = diagnose_pooled([Evaluation(lin, np.eye(3), None) for lin in (warm, nulls[2])], known_effects(),
                          ["warm", "hot"])
    visible = {(t["effect"], t["sensor"]): t["visible_fraction"] for t in doc["tested"]}
    rigid = rigid_walks(warm)
    alone = {(c.effect, c.sensor): examine(warm, c, rigid).visible
             for c in candidates(warm, np.eye(3), known_effects())}
    for key in (("bias_temperature_nonlinear", "gyro"), ("bias_temperature_nonlinear", "accel")):
        assert alone[key] >= VISIBLE_MIN and visible[key] >= alone[key]
    assert doc["findings"] == [] and doc["shared"] == ["S_a", "M_g", "k_a", "k_g"]


def test_a_scale_temperature_no_session_sees_is_named_and_held_out_by_session():
    effects = {"accel_scale_temperature": {"ppm_per_C": PPM}}
    parts = [_fitted(T, effects, seed=3 + i) for i, T in enumerate(TEMPERATURES)]
    doc = diagnose_pooled([Evaluation(lin, np.eye(3), None) for lin in parts], known_effects(), ["a", "b", "c"])
    assert [f["effect"] for f in doc["findings"]] == ["accel_scale_temperature"], doc["findings"]
    f = doc["findings"][0]
    np.testing.assert_allclose(f["parameters"]["ppm_per_C"], PPM, atol=0.5)  # noise-free: 0.07 measured
    assert f["heldout_rms_after"] < 0.2 * f["heldout_rms_before"] and f["heldout_z"] > 1.645
    assert set(f["window_sessions"]) <= {"a", "c"}  # at 25 degC the term is zero


def test_a_gyro_walk_each_warm_up_hides_in_its_k_is_found_with_one_k():
    # in a warm-up the temperature rises like a drift: each session's own k takes up the walk
    unit = _consumer_unit(0)
    rests, cals = [], []
    for k, ambient in enumerate((5.0, 35.0)):
        imu = unit.model_copy(update={"thermal": unit.thermal.model_copy(update={"ambient_C": ambient,
                                                                                  "initial_C": ambient})})
        out, truth = simulate_arrays("gimbal", {}, k, imu=imu, env={"gravity_m_s2": G}, grid_deg=45.0,
                                     n_rotations=30, rest_s=3.0)
        rests.append(rests_from_truth(out, truth)[0])
        cals.append(truth.calibration)
    assert [gyro_walk_intensity(r, c["gyro"], True, None)[0][0] for r, c in zip(rests, cals)] == [0.0, 0.0]
    _, q_g = pooled_walks(rests, [c["accel"] for c in cals], [c["gyro"] for c in cals], G)
    assert GYRO_RW**2 / 10 < q_g < GYRO_RW**2 * 10


def test_pooled_candidates_keep_what_each_sessions_own_carry(nulls):
    """A pooled candidate keeps its held-out sensor and its rejection rule, and a warm-up's profile
    stacks each session's own columns at the asked time constant."""
    warm = _fitted(25.0, None, warming=True)
    parts = [warm, nulls[2]]
    pooled = pooled_candidates(parts, [np.eye(3)] * 2, known_effects())
    lag = next(c for c, _ in pooled if c.effect == "thermal_lag")
    assert lag.sensor == "temperature" and lag.heldout_sensor in ("accel", "gyro") and lag.rejects is not None
    c, own = next((c, own) for c, own in pooled if c.effect == "warmup_transient" and c.sensor == "gyro")
    expected = np.vstack([o.profile(50.0).columns if o is not None else np.zeros((len(lin.r), 3))
                          for o, lin in zip(own, parts)])
    np.testing.assert_array_equal(c.profile(50.0).columns, expected)
    assert c.profile(50.0).fixed == {"tau_s": 50.0}

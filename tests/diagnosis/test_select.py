"""A catalogue term's column is what the term, applied to the readings by the simulator, does to
every row of the fitted model: rest means, the motions' accelerometer samples, and the rows the
motions' gyro samples reach through the integrated attitude; a term inside a larger one outside
the catalogue (one lever arm in a lever arm per axis) is tested against it."""

from __future__ import annotations

import copy
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from forward_synth import G, joint_model, noise_free_imu, rests_from_truth, small_gimbal

from imupipe.diagnosis.forward import MotionAccel
from imupipe.diagnosis.linearised import fit
from imupipe.diagnosis.select import (
    BLOCK_S,
    LONG_BLOCKS,
    STRETCHES,
    Candidate,
    _cubic_slope,
    _gain_z,
    _leave_one_out,
    _row_groups,
    _stretch_of_rows,
    candidates,
    examine,
    rigid_solver,
    rigid_walks,
    select,
    time_blocks,
    wild_p,
)
from imupipe.effects.earth_rotation import EARTH_RATE
from imupipe.models import T_REF_C
from imupipe.sim.api import known_effects, simulate_arrays
from imupipe.sim.sensor import first_order_lag

SEED = 3
EFFECTS = {
    "gyro_g_sensitivity": {"G": [[2e-4, -1e-4, 0.0], [0.0, 1e-4, 3e-4], [-2e-4, 0.0, 1e-4]]},
    "accel_scale_temperature": {"ppm_per_C": [300.0, -200.0, 100.0]},
    "bias_temperature_nonlinear": {"k2_per_C2": [2e-5, -1e-5, 3e-5], "sensor": "gyro"},
    "gyro_scale_temperature": {"ppm_per_C": [300.0, -200.0, 100.0]},
    "gyro_scale_asymmetry": {"eps": [2e-3, -1e-3, 1.5e-3]},
}


def _response(fitted, effect: str, params: dict) -> tuple:
    """The fitted model's residual change when the simulator applies ``effect`` to the readings,
    and the term's candidate."""
    imu, model, lin = fitted[0], fitted[3], fitted[-1]
    out2, truth2 = simulate_arrays("gimbal", {effect: params}, SEED, imu=imu, env={"gravity_m_s2": G},
                                   grid_deg=60.0, rest_s=2.0, step_s=1.5, n_rotations=6, rotation_s=2.0)
    rests2, turns2 = rests_from_truth(out2, truth2)
    # the same model, the readings with the term in them (rests' means, motions' samples)
    m2 = copy.copy(model)
    m2.y_a, m2.y_g = rests2.need("accel"), rests2.need("gyro")
    m2.motions = dataclasses.replace(model.motions, y=np.concatenate(turns2.gyro))
    m2.accel = MotionAccel.select(out2.t, out2.raw["accel"], rests2, turns2)
    dr = m2.residuals(lin.x_g, lin.x_l)[0] - lin.r
    sensor = params.get("sensor", "accel" if effect.startswith("accel") else "gyro")
    (c,) = [c for c in candidates(lin, np.eye(3), known_effects()) if (c.effect, c.sensor) == (effect, sensor)]
    return lin, dr, c


@pytest.mark.parametrize("effect", sorted(EFFECTS))
def test_a_terms_column_is_what_the_term_does_to_every_row(fitted, effect):
    params = EFFECTS[effect]
    lin, dr, c = _response(fitted, effect, params)
    theta = np.ravel(next(v for k, v in params.items() if k != "sensor"))
    predicted = -c.columns @ theta  # the term in the readings: the residual grows by it
    motion = ~(lin.rows.of("accel_rest") | lin.rows.of("gyro_rest"))
    assert np.linalg.norm(dr[motion]) > 0.2 * np.linalg.norm(dr)  # the motions carry much of it
    assert np.linalg.norm(dr - predicted) < 0.02 * np.linalg.norm(dr)
    t = examine(lin, c, rigid_walks(lin))
    assert 0 <= t.visible <= 1 and t.mde > 0


def test_earths_rate_is_sensed_through_the_gyros_scale_matrix(fitted):
    """Earth's rate is an input of the gyro: its column goes through the scale matrix (a few %
    from unity on this unit), as the simulator applies it. At the pole all of it is vertical."""
    lin, dr, c = _response(fitted, "earth_rotation", {"latitude_deg": 90.0})
    S_g = np.linalg.inv(lin.model.unpack(lin.x_g)["M_g"])
    assert np.abs(S_g - np.eye(3)).max() > 0.01
    assert np.linalg.norm(dr + c.columns[:, 0] * EARTH_RATE) < 0.002 * np.linalg.norm(dr)


def test_held_out_stretches_are_whole_rests_and_motions_contiguous_in_time(fitted):
    lin = fitted[-1]
    stretch = _stretch_of_rows(lin)
    data = stretch >= 0
    assert not data[lin.rows.of("walk_gyro") | lin.rows.of("walk_accel") | lin.rows.of("turn")].any()
    for block in ("accel_rest", "accel_motion"):  # one stretch per rest / per motion
        rows = lin.rows.of(block)
        unit = lin.rows.index[rows] if block == "accel_rest" else lin.model.accel.motion[lin.rows.index[rows]]
        for i in np.unique(unit):
            assert len(np.unique(stretch[rows][unit == i])) == 1
    rest = lin.rows.of("accel_rest")
    assert np.array_equal(stretch[rest], stretch[lin.rows.of("gyro_rest")])  # a rest's two triads together
    order = np.argsort(lin.rows.t[rest], kind="stable")
    assert np.all(np.diff(stretch[rest][order]) >= 0)  # contiguous in time
    assert len(np.unique(stretch[data])) == min(STRETCHES, lin.model.n)


def test_with_sessions_each_session_is_cut_into_stretches_of_its_own(fitted):
    lin = fitted[-1]
    group = _row_groups(lin)
    data = group >= 0
    t_group = np.bincount(group[data], lin.rows.t[data]) / np.maximum(np.bincount(group[data]), 1)
    session = np.where(data, t_group[group] > np.quantile(t_group, 0.3), 0).astype(int)  # of unequal length
    stretch = _stretch_of_rows(lin, 2, session)
    assert np.array_equal(stretch >= 0, data)
    for s, halves in ((0, {0, 1}), (1, {2, 3})):
        mine = data & (session == s)
        assert set(stretch[mine]) == halves
        per_half = [len(np.unique(group[mine & (stretch == h)])) for h in sorted(halves)]
        assert abs(per_half[0] - per_half[1]) <= 1  # each half of the session's rests and motions
        first, second = (lin.rows.t[mine & (stretch == h)] for h in sorted(halves))
        assert first.max() <= second.min()


def test_leave_one_out_in_closed_form_is_the_refit_without_the_group():
    rng = np.random.default_rng(3)
    X, r, g = rng.normal(size=(60, 3)), rng.normal(size=60), np.repeat(np.arange(6), 10)
    chi, predicted = _leave_one_out(X, r, g)
    for k in range(6):
        test = g == k
        theta = np.linalg.lstsq(X[~test], r[~test], rcond=None)[0]
        e = r[test] - X[test] @ theta
        assert np.allclose(predicted[test], e)
        full = r - X @ np.linalg.lstsq(X, r, rcond=None)[0]
        without = r[~test] - X[~test] @ theta
        assert np.isclose(chi[k], full @ full - without @ without)  # what the group adds to chi2


def _held_out_z(rng, effect: float, heterogeneous: bool) -> float:
    """A term's held-out z on a toy linear model: 40 units, the term acting in a few of them
    only (``heterogeneous``) or in all alike, leave-one-unit-out in closed form."""
    g = np.repeat(np.arange(40), 25)
    x = rng.normal(size=len(g)) * (np.where(g < 4, 3.0, 0.1) if heterogeneous else 1.0)
    X = x[:, None] / np.linalg.norm(x)
    r = effect * X[:, 0] + rng.normal(size=len(g))
    theta = np.linalg.lstsq(X, r, rcond=None)[0]
    (chi_b, _), (chi_a, _) = (_leave_one_out(A, r, g) for A in (X[:, :0], X))
    (sig_b, _), (sig_a, _) = (_leave_one_out(A, X @ theta, g) for A in (X[:, :0], X))
    return _gain_z(chi_b - chi_a, sig_b - sig_a)


def test_held_out_z_is_calibrated_on_nulls_and_not_penalised_by_where_the_evidence_sits():
    rng = np.random.default_rng(11)
    nulls = np.array([_held_out_z(rng, 0.0, h) for _ in range(300) for h in (False, True)])
    assert np.mean(nulls >= 1.645) <= 0.06  # one-sided 5 %: a term without effect rarely passes
    for heterogeneous in (False, True):  # noncentrality 100: z about sqrt(100) / 2 wherever it sits
        z = np.median([_held_out_z(rng, 10.0, heterogeneous) for _ in range(50)])
        assert 4.0 < z < 6.0


def test_a_thermal_lags_column_is_what_the_lagged_read_out_does_to_every_row():
    """The biases follow the die, the model the lagged read-out: both triads read k tau dT_read/dt
    more, through the motions' attitude too. The read-out's rate is its slope over ``RATE_S``,
    which blurs the lag's start at power-on (the first tau seconds): hence 5 %."""
    imu = noise_free_imu(SEED)
    imu["thermal"] = {**imu["thermal"], "self_heating_C": 40.0, "tau_s": 600.0}
    out, truth = small_gimbal(SEED, imu)
    tau = 60.0
    lagged = dataclasses.replace(out, temperature=first_order_lag(out.t, out.temperature, tau))
    model = joint_model(lagged, truth)[0]
    lin = fit(model, max_iter=5)
    die = copy.copy(model)  # the same model (its gravity parametrisation too) on the die's temperature
    die._temperature = (out.t, out.temperature)
    die.dT = die.rest_temperature() - T_REF_C
    die.dT_gyro, die.dT_acc = die.temperature_at(die.motions.t) - T_REF_C, die.temperature_at(die.accel.t) - T_REF_C
    dr = lin.r - die.residuals(lin.x_g, lin.x_l)[0]
    (c,) = [c for c in candidates(lin, np.eye(3), known_effects()) if c.effect == "thermal_lag"]
    predicted = -c.columns[:, 0] * tau
    for block in ("accel_rest", "gyro_rest", "accel_motion", "turn"):  # every row the read-out reaches
        assert np.linalg.norm(dr[lin.rows.of(block)]) > 0.1 * np.linalg.norm(dr)
    assert np.linalg.norm(dr - predicted) < 0.05 * np.linalg.norm(dr)


def test_one_lever_arm_is_named_and_a_lever_arm_per_axis_is_only_part_of_the_story(fitted):
    """A size effect (each accelerometer axis at its own point) holds one lever arm inside it: the
    lever arm is accepted, and the per-axis term's further directions are tested beyond it. A
    term that only takes up part of those directions (here a made-up one: the x axis's offset
    along y) is not stood behind either."""
    lin = fitted[-1]
    (c,) = [c for c in candidates(lin, np.eye(3), known_effects()) if c.effect == "lever_arm"]
    name, per_axis = c.within
    inside = Candidate("inside", "accel", "motion", ["d_xy"], per_axis[:, [1]], lambda th: {})
    noise = np.random.default_rng(5).standard_normal(len(lin.r))
    d = 0.01
    for term, beyond in ((c.columns @ [d, -d, d], ""), (per_axis @ (d * np.eye(3).ravel()), name)):
        shifted = dataclasses.replace(lin, r=noise - term)
        _, accepted = select(shifted, [examine(shifted, c), examine(shifted, inside)])
        assert [f.tested.candidate.effect for f in accepted] == ["lever_arm", "inside"][:1 + bool(beyond)]
        assert all(f.beyond == beyond for f in accepted)


def test_long_blocks_keep_flicker_noise_from_passing_for_a_term_and_still_find_one():
    """Flicker noise (1/f) is correlated far beyond 5 s: over 5-s blocks the wild bootstrap takes
    its wander along a term that changes every 150 s (as orientations do) for the term, over
    ``LONG_BLOCKS`` spans it does not; a term of 5 standard errors is still found over them."""
    t = np.arange(0.0, 1800.0, 0.5)
    n = len(t)
    c = np.sign(np.sin(2 * np.pi * t / 300))
    Cp = (c - c.mean())[:, None]
    spans = time_blocks(SimpleNamespace(rows=SimpleNamespace(t=t)), long=True)  # what it reads of a fit
    assert len(np.unique(spans)) == LONG_BLOCKS + 1  # the last sample opens a span of its own
    short = np.floor(t / BLOCK_S).astype(np.int64)
    f = np.fft.rfftfreq(n, 0.5)
    shape = np.r_[0.0, f[1:] ** -0.5]
    false_short = false_long = found = 0
    for seed in range(100):
        rng = np.random.default_rng(seed)
        pink = np.fft.irfft(np.fft.rfft(rng.normal(size=n)) * shape, n)
        r = rng.normal(size=n) + 3 * pink / pink.std()
        false_short += wild_p(Cp, r, short) < 0.01
        false_long += wild_p(Cp, r, spans) < 0.01
        found += wild_p(Cp, rng.normal(size=n) + 5 * Cp[:, 0] / np.linalg.norm(Cp), spans) < 0.01
    assert false_short >= 10 and false_long <= 3 and found >= 80, (false_short, false_long, found)


def test_cubic_slope_is_savitzky_golay_without_scipy_signal():
    from scipy.signal import savgol_filter

    rng = np.random.default_rng(5)
    y = np.cumsum(rng.normal(size=(200, 3)), axis=0)
    for win in (5, 11, 199):
        want = savgol_filter(y, win, 3, deriv=1, delta=0.01, axis=0)
        assert np.allclose(_cubic_slope(y, win, 0.01), want, rtol=1e-11, atol=1e-11 * np.abs(want).max())
        assert np.allclose(_cubic_slope(y[:, 0], win, 0.01), want[:, 0], rtol=1e-11, atol=1e-11 * np.abs(want).max())


def test_the_rigid_solver_factors_rigid_walks_system_in_j_ls_own_values_and_restores_them(fitted):
    """The structure cells' solver with the walks held still is ``rigid_walks``' system to the bit,
    factored without a copy of J_l's values, which are left exactly as they were."""
    lin = fitted[-1]
    assert (lin.rows.of("walk_gyro") | lin.rows.of("walk_accel")).any()
    before = lin.J_l.data.copy()
    solver = rigid_solver(lin)
    assert np.array_equal(lin.J_l.data, before)
    assert solver.J_l is None and solver.J_g is None  # solves only
    full = rigid_walks(lin)[0]
    assert not np.array_equal(full.S, lin.system.S)  # the walks do weigh differently
    rng = np.random.default_rng(0)
    g, l = rng.normal(size=(lin.J_g.shape[1], 3)), rng.normal(size=(lin.J_l.shape[1], 3))
    assert np.array_equal(solver.S, full.S)
    for a, b in zip(solver.solve(g, l), full.solve(g, l), strict=True):
        assert np.array_equal(a, b)

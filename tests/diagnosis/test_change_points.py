"""``pelt_l2`` is ruptures' PELT with its least-squares cost, vectorised: the same break points."""

from __future__ import annotations

import numpy as np
import ruptures

from imupipe.diagnosis.residual_map import lone_rests, pelt_l2


def test_pelt_l2_finds_ruptures_break_points():
    z = np.random.default_rng(4).normal(size=(120, 3))
    z[40:] += 1.0
    z[90:] -= 2.0
    pen = 3 * 2 * np.log(len(z))
    assert pelt_l2(z, pen) == ruptures.Pelt(model="l2", min_size=3, jump=1).fit(z).predict(pen=pen)[:-1] == [40, 90]


def test_pelt_l2_agrees_with_ruptures_on_nulls_steps_and_outliers():
    for seed in range(40):
        rng = np.random.default_rng(seed)
        n = int(rng.integers(12, 120))
        z = rng.normal(size=(n, 3))
        for _ in range(int(rng.integers(0, 3))):  # none to two steps
            z[int(rng.integers(0, n)):] += rng.normal(0, 1.5, 3)
        z[int(rng.integers(0, n))] += 8.0 * (seed % 3 == 0)  # an outlier rest in some
        pen = 3 * 2 * np.log(n)
        assert pelt_l2(z, pen) == ruptures.Pelt(model="l2", min_size=3, jump=1).fit(z).predict(pen=pen)[:-1], seed


def test_a_lone_rest_is_found_and_a_step_is_not_one():
    z = np.random.default_rng(7).normal(size=(300, 3))
    assert len(lone_rests(z)[0]) == 0  # a null series
    bad = z.copy()
    bad[120] += [0.0, -3.0, 12.0]  # a rest that turned slowly: off from both neighbours
    assert list(lone_rests(bad)[0]) == [120]
    step = z.copy()
    step[150:] += [0.0, 0.0, 12.0]  # a bias jump: every rest after it moves together
    assert len(lone_rests(step)[0]) == 0
    assert pelt_l2(np.delete(bad, lone_rests(bad)[0], axis=0), 3 * 2 * np.log(299)) == []  # no step either side
    assert len(lone_rests(5 * z)[0]) == 0  # a series that misfits everywhere: judged by its own scatter
    assert list(lone_rests(5 * bad)[0]) == [120]


def test_lone_rests_keep_their_false_alarms_under_the_level():
    alarms = sum(len(lone_rests(np.random.default_rng(seed).normal(size=(500, 3)))[0]) > 0 for seed in range(400))
    assert alarms <= 4  # 0.1 % family-wise: 0.4 expected in 400 series, 4 has p < 0.001

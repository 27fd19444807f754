"""The naming traps a recording cannot resolve: an accepted term gets a rival when the rival is
significant in its place and the term adds nothing beyond the rival; nested terms are left to
parsimony; Earth's rate stands where a known latitude agrees. The rule on stand-in statistics
(the sessions that exercise it end to end are the bench's: a thermal lag whose start-up falls
in one long rest)."""

from __future__ import annotations

import numpy as np

from imupipe.diagnosis import select
from imupipe.diagnosis.select import Candidate, Finding, _earth_rivals, _rivals
from imupipe.effects.earth_rotation import EARTH_RATE

Q = 0.05


def _tested(effect: str, columns: np.ndarray) -> select.Tested:
    c = Candidate(effect, "gyro", "static", ["a"] * columns.shape[1], columns, lambda th: {})
    return select.Tested(c, columns, 1.0, [], 1.0)


def _stat(p_alone: dict, p_beyond: dict):
    """p of a term given the others: ``p_alone`` when no rival is among them, else ``p_beyond``."""
    def stat(t: select.Tested, others: list[Finding]):
        rival = [g.tested.candidate.effect for g in others if g.tested.candidate.effect in p_beyond]
        p = p_beyond[rival[0]] if rival and t.candidate.effect not in p_beyond else p_alone[t.candidate.effect]
        return 0.0, p, p
    return stat


def test_a_term_the_rival_explains_as_well_gets_it_and_one_it_goes_beyond_does_not():
    rng = np.random.default_rng(0)
    lag, warm, quad = (_tested(e, rng.standard_normal((50, k))) for e, k in
                       (("thermal_lag", 1), ("warmup_transient", 3), ("bias_temperature_nonlinear", 3)))
    f = Finding(lag, 10.0, 1e-4, -5.0)
    # the warm-up is significant alone and the lag adds nothing beyond it; the quadratic is not significant
    _rivals([f], [lag, warm, quad], _stat({"warmup_transient": 1e-4, "bias_temperature_nonlinear": 0.3},
                                          {"warmup_transient": 0.4}), Q)
    assert f.rivals == ["warmup_transient"]
    g = Finding(lag, 10.0, 1e-4, -5.0)
    # the lag still significant beyond the warm-up: it is named
    _rivals([g], [lag, warm, quad], _stat({"warmup_transient": 1e-4, "bias_temperature_nonlinear": 0.3},
                                          {"warmup_transient": 1e-3}), Q)
    assert g.rivals == []


def test_a_term_inside_a_larger_one_is_not_its_rival():
    rng = np.random.default_rng(1)
    G = rng.standard_normal((50, 9))
    earth = _tested("earth_rotation", G[:, :1] @ np.ones((1, 1)))
    g_sens = _tested("gyro_g_sensitivity", G)
    f = Finding(earth, 10.0, 1e-4, -5.0)
    _rivals([f], [earth, g_sens], _stat({"gyro_g_sensitivity": 1e-4}, {"gyro_g_sensitivity": 0.9}), Q)
    assert f.rivals == []


def test_earths_rate_stands_behind_itself_only_where_the_known_latitude_agrees():
    rng = np.random.default_rng(2)
    G = rng.standard_normal((50, 9))
    at_48 = EARTH_RATE * np.sin(np.radians(48.0))
    column = G[:, :1] / np.linalg.norm(G[:, :1]) / (0.05 * at_48)  # the rate's sd: 5 % of Earth's at 48 deg
    earth, g_sens = _tested("earth_rotation", column), _tested("gyro_g_sensitivity", G)
    rp = np.zeros(50)

    for latitude, rate, rival in ((None, at_48, True), (48.0, at_48, False), (48.0, 1.02 * at_48, False),
                                  (48.0, 0.5 * at_48, True), (-48.0, at_48, True)):
        f = Finding(earth, 10.0, 1e-4, -5.0, theta=np.array([rate]))
        _earth_rivals([f], [earth, g_sens], rp, latitude)
        assert (f.rivals == ["gyro_g_sensitivity"]) == rival, (latitude, rate)

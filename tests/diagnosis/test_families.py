"""A session's findings come from three families of tests (catalogue, structure cells, the map's
chi2/dof cells): q is split among them so that a null session reports anything at most q of the time."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2, norm

from imupipe.diagnosis.diagnose import family_levels, map_unknown_cells, noise_misfit
from imupipe.diagnosis.library import bootstrap_draws
from imupipe.diagnosis.residual_map import benjamini_hochberg

Q = 0.05
SESSIONS = 4000


def _null_families(rng, n: int) -> dict[str, np.ndarray]:
    """p-values (n sessions, tests) of null sessions' families, dependent as the real ones are:
    10 catalogue terms sharing rows (equicorrelated scores), 12 structure cells (3 libraries: all
    axes and each axis, the all-axes statistic the sum of the axes'), the map's cells (sums of 1
    to 10 neighbouring bins of shared rows, overlapping as the map's variables do)."""
    z = np.sqrt(0.5) * rng.normal(size=(n, 1)) + np.sqrt(0.5) * rng.normal(size=(n, 10))
    axes = rng.chisquare(11, (n, 3, 3))
    structure = np.concatenate([chi2.sf(axes.sum(axis=2), 33), chi2.sf(axes, 11).reshape(n, 9)], axis=1)
    e = rng.chisquare(50, (n, 40))
    cells = [chi2.sf(e[:, a:a + w].sum(axis=1), 50 * w) for w in range(1, 11) for a in range(0, 40 - w + 1, 2 * w)]
    return {"catalogue": 2 * norm.sf(np.abs(z)), "structure": structure, "map": np.column_stack(cells)}


def _session_rate(levels: dict[str, float], seed: int) -> float:
    fam = _null_families(np.random.default_rng(seed), SESSIONS)
    hits = [any(benjamini_hochberg(fam[f][i], levels[f]).any() for f in fam) for i in range(SESSIONS)]
    return float(np.mean(hits))


def test_a_null_session_reports_anything_at_most_q_of_the_time():
    levels = family_levels(Q)
    assert abs(sum(levels.values()) - Q) < 1e-15
    rate = _session_rate(levels, 1)
    assert rate <= Q + 3 * np.sqrt(Q * (1 - Q) / SESSIONS)
    # each family at q on its own: a null session reports something well above q of the time
    assert _session_rate(dict.fromkeys(levels, Q), 1) > Q + 3 * np.sqrt(Q * (1 - Q) / SESSIONS)


def test_map_unknowns_are_discovered_at_the_maps_share_not_by_its_own_flags():
    def cell(p, variable="time s", flagged=True):
        return {"sensor": "accel", "axes": ["x"], "regime": "static", "variable": variable, "p_value": p,
                "flagged": flagged}

    weak = {"cells": [cell(0.003), *[cell(0.5, flagged=False)] * 9]}  # flagged by the map at q = 0.05
    assert map_unknown_cells(weak, Q) and not map_unknown_cells(weak, family_levels(Q)["map"])
    strong = {"cells": [cell(1e-8), cell(1e-9, "structure"), *[cell(0.5, flagged=False)] * 9]}
    found = map_unknown_cells(strong, family_levels(Q)["map"])
    assert [c["variable"] for c in found] == ["time s"]  # structure cells are tested given the findings
    assert map_unknown_cells(None, Q) == []


def test_a_sensor_misfits_when_its_whole_cell_is_discovered_not_one_bin_of_it():
    def cell(sensor, variable, p):
        return {"sensor": sensor, "axes": ["x", "y", "z"], "regime": "static", "variable": variable, "p_value": p,
                "flagged": p < 0.05}

    filler = [cell("gyro", "all", 0.5)] * 9
    assert noise_misfit({"cells": [cell("accel", "all", 1e-7), *filler]}, Q) == {"accel"}
    assert noise_misfit({"cells": [cell("accel", "temperature degC", 1e-7), *filler]}, Q) == frozenset()
    assert noise_misfit({"cells": [cell("accel", "all", 0.003), *filler]}, Q) == frozenset()  # not at the map's share
    assert noise_misfit(None, Q) == frozenset()


def test_the_bootstrap_floor_never_decides_a_structure_discovery():
    for tests, level in ((12, family_levels(Q)["structure"]), (3, Q), (40, 0.001)):
        draws = bootstrap_draws(tests, level)
        assert 1 / (draws + 1) <= 0.5 * level / tests

"""imupipe.tails against scipy.stats: the same numbers, bit for bit, edges included."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from imupipe import tails

EDGES = [-np.inf, -1.0, 0.0, 1e-300, 0.3, 1.0, 7.5, 1e3, np.inf, np.nan]
DOFS = [-1.0, 0.0, 0.5, 1.0, 3.0, 27.0, np.nan]
PROBS = [-0.1, 0.0, 1e-300, 1e-12, 0.05, 0.5, 0.99, 1.0, 1.1, np.nan]


def _same(a, b) -> bool:
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_tails_equal_scipy_stats():
    rng = np.random.default_rng(0)
    x, dof = np.abs(rng.normal(size=500)) * 20, rng.integers(1, 60, 500).astype(float)
    p, z = rng.uniform(size=500), rng.normal(size=500) * 4
    assert _same(tails.chi2_sf(x, dof), stats.chi2.sf(x, dof))
    assert _same(tails.chi2_isf(p, dof), stats.chi2.isf(p, dof))
    assert _same(tails.chi2_ppf(p, dof), stats.chi2.ppf(p, dof))
    assert _same(tails.norm_sf(z), stats.norm.sf(z))
    assert _same(tails.norm_isf(p), stats.norm.isf(p))
    assert _same(tails.t_sf(z, dof), stats.t.sf(z, dof))
    for k in DOFS:  # outside the support and at its ends; scalars in, scalars out
        for v in EDGES:
            assert _same(tails.chi2_sf(v, k), stats.chi2.sf(v, k)), (v, k)
            assert _same(tails.t_sf(v, k), stats.t.sf(v, k)), (v, k)
            assert np.ndim(tails.chi2_sf(v, k)) == 0
        for q in PROBS:
            assert _same(tails.chi2_isf(q, k), stats.chi2.isf(q, k)), (q, k)
            assert _same(tails.chi2_ppf(q, k), stats.chi2.ppf(q, k)), (q, k)
    for q in PROBS:
        assert _same(tails.norm_isf(q), stats.norm.isf(q)), q
    for v in EDGES:
        assert _same(tails.norm_sf(v), stats.norm.sf(v)), v


@pytest.mark.parametrize("d1", [2, 6, 12])
def test_f_tail_of_an_even_numerator_is_scipys(d1):
    """The drift check's F-test tail, a finite sum for an even numerator, is scipy.stats' ``f.sf``
    (to 1e-11: a different formula, not bit for bit)."""
    for d2 in (1.0, 3.5, 9.0, 40.0, 700.0):
        for x in (0.0, 1e-3, 0.4, 1.0, 3.0, 12.0, 300.0):
            want = float(stats.f.sf(x, d1, d2))
            assert np.isclose(tails.f_sf(x, d1, d2), want, rtol=1e-11, atol=1e-300), (d2, x)
    with pytest.raises(ValueError, match="even"):
        tails.f_sf(1.0, 5, 10.0)

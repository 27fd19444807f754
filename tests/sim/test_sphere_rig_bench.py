"""The Monte Carlo bench's estimator and Cramer-Rao bound behave as they must."""

from __future__ import annotations

import numpy as np
from bench_scripts import load_bench


def _bench():
    return load_bench("sphere_rig_tables")


def test_estimator_is_exact_without_noise():
    b = _bench()
    x = b.positions(np.random.default_rng(0), 30, "sphere")
    y = x @ b.M_A.T + b.B
    M, bias = b.estimate(y, b.M_A @ b.E[1] + b.B, b.M_A @ b.E[0] + b.B)
    np.testing.assert_allclose(bias, b.B, atol=1e-12)
    np.testing.assert_allclose(M, np.linalg.inv(b.M_A), atol=1e-12)


def test_monte_carlo_spread_is_not_below_the_cramer_rao_bound():
    b = _bench()
    r = b.monte_carlo(200, 200, "sphere", np.random.default_rng(1), 0.0)
    crb = b.crb_halfwidths(b.fisher_per_position("sphere", samples=4000), 200)
    sd = 1.96 * r["b"].std(axis=0)
    assert np.all(sd > 0.8 * crb["b"])  # 200 sets: the spread itself is uncertain by ~5 %
    assert np.all(sd < 1.5 * crb["b"])

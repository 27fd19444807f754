"""``CumulativeL2`` is ruptures' ``CostL2`` from cumulative sums: the same costs, the same PELT."""

from __future__ import annotations

import numpy as np
import ruptures
from ruptures.costs import CostL2

from imupipe.diagnosis.residual_map import CumulativeL2


def test_the_cumulative_cost_is_ruptures_l2_and_pelt_finds_the_same_breaks():
    z = np.random.default_rng(4).normal(size=(120, 3))
    z[40:] += 1.0
    z[90:] -= 2.0
    ours, theirs = CumulativeL2().fit(z), CostL2().fit(z)
    for start, end in ((0, 1), (0, 120), (3, 17), (40, 90), (89, 91)):
        assert abs(ours.error(start, end) - theirs.error(start, end)) < 1e-9 * max(1.0, theirs.error(start, end))
    pen = 3 * 2 * np.log(len(z))
    breaks = ruptures.Pelt(custom_cost=CumulativeL2(), min_size=3, jump=1).fit(z).predict(pen=pen)
    assert breaks == ruptures.Pelt(model="l2", min_size=3, jump=1).fit(z).predict(pen=pen) == [40, 90, 120]

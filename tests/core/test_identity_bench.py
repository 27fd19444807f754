"""bench/residual_identity.py's judgement of two runs' calibration.json and residual map: 1e-9
relative, or the rounding floor (other BLAS kernels' spread; for the calibration also a
hundred-thousandth of the statistical spread)."""

from __future__ import annotations

import copy

import numpy as np
from bench_scripts import load_bench


def _bench():
    return load_bench("residual_identity")


REF = {"session": "/a/s.mcap",
       "gyro": {"M": [[1.0, 0.0], [0.0, 1.0]], "sigma_M": [[1e-5, 1e-5], [1e-5, 1e-5]],
                "k": [1e-3, 2e-3], "sigma_k": [1e-4, 1e-4],
                "covariance": [[4e-10, 1e-11], [1e-11, 4e-10]],
                "joint": {"blocks": {"turn": {"chi2": 100.0, "dof": 98.0, "rows": 100, "rms": 1.0}},
                          "rms_whitened": {"turn": 1.0}}}}


def _changed(**edits):
    doc = copy.deepcopy(REF)
    doc["session"] = "/b/s.mcap"  # another folder's run: not compared
    for path, value in edits.items():
        *where, last = path.split("__")
        node = doc
        for key in where:
            node = node[key]
        node[last] = value
    return doc


def _failing(b, new, kernels=()):
    return [name for d, allowed, name, _ in b.compare_calibrations(REF, new, list(kernels), 1e-9) if d > allowed]


def test_a_parameter_moved_by_a_thousandth_of_its_standard_error_differs():
    b = _bench()
    assert _failing(b, _changed()) == []
    assert _failing(b, _changed(gyro__M=[[1.0 + 1e-12, 0.0], [0.0, 1.0]])) == []  # within 1e-9
    assert _failing(b, _changed(gyro__M=[[1.0 + 1e-8, 0.0], [0.0, 1.0]])) == ["/gyro/M"]  # 1e-3 sigma
    # a weakly determined coefficient: 1e-8 of its size is 1e-7 of its standard error
    assert _failing(b, _changed(gyro__k=[1e-3 * (1 + 1e-8), 2e-3])) == []
    assert _failing(b, _changed(gyro__k=[1e-3 * (1 + 1e-3), 2e-3])) == ["/gyro/k"]  # 1e-2 sigma


def test_a_fit_statistic_is_judged_by_its_own_spread():
    b = _bench()
    # chi2 1e-8 relative: 1e-6 of chi2 whose spread is sqrt(196) = 14
    new = _changed(gyro__joint__blocks__turn__chi2=100.0 * (1 + 1e-8))
    assert _failing(b, new) == []
    new = _changed(gyro__joint__blocks__turn__chi2=100.0 + 1e-3)  # 7e-5 of its spread
    assert _failing(b, new) == ["/gyro/joint/blocks/turn/chi2"]


def test_a_field_without_a_statistical_spread_is_allowed_ten_times_the_kernels_spread():
    b = _bench()
    moved = _changed(gyro__covariance=[[4e-10 * (1 + 1e-6), 1e-11], [1e-11, 4e-10]])
    assert _failing(b, moved) == ["/gyro/covariance"]
    # the new code on another kernel: its spread from the new run sets the floor
    other_kernel = _changed(gyro__covariance=[[4e-10 * (1 + 1e-6) * (1 + 2e-7), 1e-11], [1e-11, 4e-10]])
    assert _failing(b, moved, [other_kernel]) == []
    assert _failing(b, moved, [copy.deepcopy(moved)]) == ["/gyro/covariance"]  # a kernel that moved nothing
    reshaped = _changed(gyro__covariance=[4e-10, 1e-11])  # a kernel that changed its shape sets no floor
    assert _failing(b, moved, [reshaped]) == ["/gyro/covariance"]


def test_a_map_number_is_allowed_ten_times_its_spread_over_kernels():
    """The map's per-sample columns and document numbers by ``judge_map``: 1e-9, or ten times what
    another BLAS kernel moves them with the new code (a kernel's non-finite difference sets no floor)."""
    b = _bench()
    ref = ({"whitened": np.array([1.0, -2.0, 0.5])}, {"blocks": [{"chi2": 100.0, "p_value": 1e-4}]})
    new = ({"whitened": np.array([1.0, -2.0 * (1 + 1e-8), 0.5])}, {"blocks": [{"chi2": 100.0, "p_value": 1e-4}]})

    def failing(kernels):
        judged = b.judge_map(b.compare_maps(ref, new), [b.compare_maps(new, k) for k in kernels], 1e-9)
        return [name for d, allowed, name in judged if d > allowed]

    assert failing([]) == ["column whitened"]
    moved = ({"whitened": np.array([1.0, -2.0 * (1 + 1e-8) * (1 + 2e-9), 0.5])}, new[1])
    assert failing([moved]) == []
    assert failing([new]) == ["column whitened"]  # a kernel that moved nothing
    reshaped = ({"whitened": np.array([1.0, 2.0])}, new[1])
    assert failing([reshaped]) == ["column whitened"]
    # a document number has its own floor (a p-value's on -log10 p): the column's does not cover it
    p_new = (ref[0], {"blocks": [{"chi2": 100.0, "p_value": 1e-4 * (1 + 1e-7)}]})  # 1.1e-8 on -log10 p
    p_kernel = (ref[0], {"blocks": [{"chi2": 100.0, "p_value": 1e-4 * (1 + 2e-7)}]})
    column_kernel = (moved[0], p_new[1])
    for kernels, ok in (([column_kernel], False), ([p_kernel], True)):
        judged = b.judge_map(b.compare_maps(ref, p_new), [b.compare_maps(p_new, k) for k in kernels], 1e-9)
        assert [(name, d <= allowed) for d, allowed, name in judged if d] == [("residual_map.json/blocks[0]/p_value", ok)]

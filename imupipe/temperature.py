"""The temperature signal as the models use it: de-quantised.

A die temperature read out in coarse steps (0.125 degC for a BMI088, updated
every 1.28 s) is an errors-in-variables regressor: rest means of the steps are
biased by up to half a step, and a model fitted on them finds fake dynamics
(``research/missing-physics.md`` E15: a quantised read-out mimics a 20 s
thermal lag). The models use the read-out smoothed over ``window_s`` instead (a
local line: zero-phase, and unbiased by a steady rise at the recording's ends),
which removes the steps and, for thermal time constants of minutes, nothing else.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .models import T_REF_C

if TYPE_CHECKING:
    from scipy.interpolate import BSpline

SMOOTH_S = 30.0
RATE_S = SMOOTH_S  # s: knot spacing of the curve whose slope is the read-out's rate


def smoothed(t: np.ndarray, T: np.ndarray, window_s: float = SMOOTH_S) -> np.ndarray:
    """(n,) ``T`` (n,) at the sample times ``t`` (n,) s (sorted), smoothed: the least-squares line
    through the samples of a ``window_s`` window centred on each, at its time (the centred moving
    average, where the samples are even). Within half a window of either end the window stays
    whole, on the one side: an average over a window that shrinks there lags a rising
    temperature (a cold start's first sample by a quarter window's rise, ~0.25 degC at 2 degC/min,
    which a gyro's ``k`` made a warm-up transient in null recordings). NaN samples are skipped."""
    t = np.asarray(t, float)
    T = np.asarray(T, float)
    ok = np.isfinite(T)
    if not len(t):
        return T.copy()
    x = t - t[0]  # small numbers: the sums of squares below cancel less
    start = np.clip(x - window_s / 2, 0.0, max(x[-1] - window_s, 0.0))
    lo = np.searchsorted(x, start, "left")
    hi = np.searchsorted(x, start + window_s, "right")

    def window_sum(v: np.ndarray) -> np.ndarray:  # over each sample's window, NaN samples left out
        c = np.r_[0.0, np.cumsum(np.where(ok, v, 0.0))]
        return c[hi] - c[lo]

    y = np.where(ok, T, 0.0)
    n, s_x, s_T, s_xx, s_xT = map(window_sum, (np.ones_like(x), x, y, x * x, x * y))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_x, mean_T = s_x / n, s_T / n
        var_x = s_xx / n - mean_x**2
        slope = np.where(var_x > 1e-12 * window_s**2, (s_xT / n - mean_x * mean_T) / var_x, 0.0)
        out = mean_T + slope * (x - mean_x)
    return np.where(n > 0, out, np.nan)


def rate_curve(t: np.ndarray, T: np.ndarray, t_first: float, t_last: float, trim: bool = True) -> BSpline:
    """The temperature ``T`` (n,) degC at ``t`` (n,) s as a least-squares cubic spline with knots
    ``RATE_S`` apart (at quantiles of its samples): the read-out's steps average out within each
    interval, and its slope is smooth where a difference of the steps would not be. ``trim``: fitted
    half a ``SMOOTH_S`` window in from [``t_first``, ``t_last``] and extrapolated to them (fitted to
    the ends as well, a gyro thermal lag's columns left a warm-up transient named beside it:
    tests/diagnosis/test_gyro_terms.py); extrapolated beyond; a line when too short."""
    from scipy.interpolate import BSpline, make_lsq_spline

    t, T = np.asarray(t, float), np.asarray(T, float)
    if trim and t_last - t_first > 2 * SMOOTH_S:
        t_first, t_last = t_first + SMOOTH_S / 2, t_last - SMOOTH_S / 2
    ok = np.isfinite(T) & (t >= t_first) & (t <= t_last)
    t, idx = np.unique(t[ok], return_index=True)
    T = T[ok][idx]
    if len(t) < 2:
        return BSpline(np.r_[t_first, t_first, t_last, t_last], np.full(2, T[0] if len(T) else T_REF_C), 1)
    degree = 3 if len(t) >= 8 else 1
    inner = int((t[-1] - t[0]) // RATE_S) - 1
    inner = min(max(inner, 0), len(t) - degree - 1)
    knots = np.r_[[t[0]] * (degree + 1), np.quantile(t, np.linspace(0, 1, inner + 2)[1:-1]), [t[-1]] * (degree + 1)]
    # the banded normal equations: scipy's default QR costs samples x knots (3.4 s for 4 h at
    # 100 Hz, 0.18 s this way; the curves agree to 1e-12 degC)
    return make_lsq_spline(t, T, knots, k=degree, method="norm-eq")


def temperature_rate(curve: BSpline, t0: np.ndarray, t1: np.ndarray | None = None) -> np.ndarray:
    """(n,) degC/s: the slope of ``curve`` at ``t0`` (n,) s, or its mean over [``t0``, ``t1``]."""
    t0 = np.asarray(t0, float)
    if t1 is None:
        return curve.derivative()(t0)
    width = np.asarray(t1, float) - t0
    return np.where(width > 0, (curve(t1) - curve(t0)) / np.where(width > 0, width, 1.0),
                    curve.derivative()(t0))

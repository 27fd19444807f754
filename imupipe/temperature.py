"""The temperature signal as the models use it: de-quantised.

A die temperature read out in coarse steps (0.125 degC for a BMI088, updated
every 1.28 s) is an errors-in-variables regressor: rest means of the steps are
biased by up to half a step, and a model fitted on them finds fake dynamics
(``research/missing-physics.md`` E15: a quantised read-out mimics a 20 s
thermal lag). The models use the zero-phase moving average of the read-out over
``window_s`` instead, which removes the steps and, for thermal time constants of
minutes, nothing else.
"""

from __future__ import annotations

import numpy as np

SMOOTH_S = 30.0


def smoothed(t: np.ndarray, T: np.ndarray, window_s: float = SMOOTH_S) -> np.ndarray:
    """(n,) the centred moving average of ``T`` (n,) over ``window_s`` seconds (shrinking at the
    ends), at the sample times ``t`` (n,) s (sorted). NaN samples are skipped."""
    t = np.asarray(t, float)
    T = np.asarray(T, float)
    ok = np.isfinite(T)
    c = np.concatenate([[0.0], np.cumsum(np.where(ok, T, 0.0))])
    k = np.concatenate([[0], np.cumsum(ok)])
    lo = np.searchsorted(t, t - window_s / 2, "left")
    hi = np.searchsorted(t, t + window_s / 2, "right")
    n = k[hi] - k[lo]
    return np.divide(c[hi] - c[lo], n, out=np.full(len(t), np.nan), where=n > 0)

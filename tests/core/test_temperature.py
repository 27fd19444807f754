"""The de-quantised temperature the models use (``imupipe.temperature.smoothed``)."""

from __future__ import annotations

import numpy as np

from imupipe.temperature import SMOOTH_S, smoothed


def test_a_quantised_cold_start_is_smoothed_without_lag_at_either_end():
    t = np.arange(0.0, 300.0, 0.1)
    T = 5.0 + 20.0 * (1 - np.exp(-t / 600.0))  # 2 degC/min at power-on
    read_out = np.round(T / 0.125) * 0.125
    error = np.abs(smoothed(t, read_out) - T)
    assert error.max() < 0.02  # a shrinking average is 0.25 degC off at the first sample
    inner = (t > SMOOTH_S) & (t < t[-1] - SMOOTH_S)
    window = SMOOTH_S / 0.1
    np.testing.assert_allclose(smoothed(t, read_out)[inner],
                               np.convolve(read_out, np.ones(int(window) + 1) / (window + 1), "same")[inner],
                               atol=2e-3)  # the centred moving average inside


def test_missing_samples_are_skipped_and_a_window_without_any_is_nan():
    t = np.arange(0.0, 200.0, 1.0)
    T = 20.0 + 0.01 * t
    T[50:60] = np.nan
    s = smoothed(t, T)
    np.testing.assert_allclose(s, 20.0 + 0.01 * t, atol=1e-9)  # a line is kept exactly
    T[20:120] = np.nan
    assert np.isnan(smoothed(t, T)[70]) and np.isfinite(smoothed(t, T)[10])

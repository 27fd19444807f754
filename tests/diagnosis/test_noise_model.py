"""The residual map's noise model: one raw sample's white noise from the rests' successive
differences, pooled over the rests that agree."""

from __future__ import annotations

import numpy as np

from imupipe.diagnosis.evaluate import white_noise
from imupipe.observations import Rests

SIGMA = np.array([4.9e-3, 4.9e-3, 6e-3])  # m/s^2, one sample
LSB = 2.4e-3  # m/s^2, half a sigma: the simulator's consumer accelerometer


def test_white_noise_is_pooled_over_rests_unmoved_by_drift_quantisation_or_a_vibrating_rest():
    """120 rests of 5 s at 100 Hz, each at its own offset, the first 300 s long with a thermal
    drift; one rest on a vibrating support. The pooled variance is within 3 standard errors of
    the quantised noise's (Sheppard: sigma^2 + LSB^2 / 12); the rests' median covariance (the
    noise model before) was off by its median bias and spread."""
    rng = np.random.default_rng(4)
    starts = np.r_[0.0, 305.0 + 7.0 * np.arange(119)]
    ends = np.r_[300.0, starts[1:] + 5.0]
    t = np.arange(0.0, ends[-1] + 1.0, 0.01)
    rest = np.clip(np.searchsorted(starts, t, "right") - 1, 0, len(starts) - 1)
    y = rng.normal(0, 0.5, (len(starts), 3))[rest] + SIGMA * rng.normal(size=(len(t), 3))
    y += np.outer(np.minimum(t, 300.0) / 300.0, [0.02, -0.01, 0.015])  # the warm-up's drift
    shaken = rest == 60
    y[shaken] += 0.02 * np.sin(2 * np.pi * 30 * t[shaken])[:, None]
    y = np.round(y / LSB) * LSB
    rests = Rests(starts, ends, np.full(len(starts), 500), {}, {}, np.full(len(starts), np.nan))
    var = np.diag(white_noise(rests, {"accel": (t, y)}, "accel"))
    true = SIGMA ** 2 + LSB ** 2 / 12
    samples = (ends - starts).sum() * 100
    assert np.all(np.abs(var / true - 1) < 3 * np.sqrt(3 / samples))

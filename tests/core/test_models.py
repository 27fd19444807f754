"""Calibration results: apply/predict inverse, serialisation round trips to 1e-12."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.errors import SchemaError
from imupipe.models import Calibration, TriadCalibration, triads_from_table, triads_to_table

ROUND_TRIP_TOL = 1e-12


def _triad(sensor: str, rng: np.random.Generator) -> TriadCalibration:
    M = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
    return TriadCalibration(sensor, M, rng.standard_normal(3), 1e-3 * rng.standard_normal(3),
                            solver="test", details={"sigma_b0": [1e-4] * 3})


def test_apply_inverts_predict():
    rng = np.random.default_rng(1)
    cal = _triad("accel", rng)
    x = rng.standard_normal((100, 3)) * 9.81
    T = 25 + 20 * rng.random(100)
    np.testing.assert_allclose(cal.apply(cal.predict(x, T), T), x, atol=ROUND_TRIP_TOL * 100)


def test_correction_formula_matches_contract():
    # contracts.md: x = M (y - b0 - k (T - 25))
    rng = np.random.default_rng(2)
    cal = _triad("gyro", rng)
    y, T = rng.standard_normal(3), 31.5
    expected = cal.M @ (y - cal.b0 - cal.k * (T - 25.0))
    np.testing.assert_allclose(cal.apply(y[None, :], T)[0], expected, rtol=0, atol=ROUND_TRIP_TOL)


def test_json_round_trip():
    rng = np.random.default_rng(3)
    cal = Calibration({s: _triad(s, rng) for s in ("accel", "gyro", "mag")}, {"session": "x.mcap"})
    back = Calibration.from_json(cal.to_json())
    for s in ("accel", "gyro", "mag"):
        for name in ("M", "b0", "k"):
            np.testing.assert_allclose(getattr(back[s], name), getattr(cal[s], name), rtol=0, atol=ROUND_TRIP_TOL)
    d = json.loads(cal.to_json())
    assert d["accel"]["units"] == "m/s^2" and d["gyro"]["units"] == "rad/s" and d["mag"]["units"] == "T"
    assert d["temperature_reference_C"] == 25.0 and d["session"] == "x.mcap"


def test_table_round_trip():
    rng = np.random.default_rng(4)
    triads = [_triad("accel", rng), _triad("mag", rng)]
    back = triads_from_table(triads_to_table(triads))
    for a, b in zip(triads, back):
        assert a.sensor == b.sensor and a.solver == b.solver and dict(b.details) == {"sigma_b0": [1e-4] * 3}
        np.testing.assert_allclose(b.M, a.M, rtol=0, atol=ROUND_TRIP_TOL)


def test_bad_shapes_and_units_are_named():
    with pytest.raises(SchemaError, match="accel.M has shape"):
        TriadCalibration("accel", np.eye(2))
    with pytest.raises(SchemaError, match="expects 'rad/s'"):
        TriadCalibration.from_dict("gyro", {"M": np.eye(3).tolist(), "units": "deg/s"})
    with pytest.raises(SchemaError, match="unknown sensor"):
        TriadCalibration("baro", np.eye(3))

"""Calibration results: correct raw data (``apply``), predict raw data (``predict``), serialise.

The nominal model of every triad (``spec/effects.md``)::

    y = S x + b0 + k (T - T_ref) + noise      forward model, S = M^-1
    x = M (y - b0 - k (T - T_ref))            correction

``x`` is the true input in the instrument frame (specific force m/s^2, rate
rad/s, field T), ``y`` the raw reading in the sensor's axes, ``T`` the reported
temperature in degC. Arrays are ``(n, 3)``; ``T`` is ``(n,)`` or a scalar.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa

from . import schemas
from .errors import SchemaError

FORMAT_VERSION = 1
SENSORS = ("accel", "gyro", "mag")
UNITS = {"accel": "m/s^2", "gyro": "rad/s", "mag": "T"}
T_REF_C = 25.0


@dataclass(frozen=True)
class TriadCalibration:
    """One triad's nominal calibration and what is known of its uncertainty.

    ``M``: (3, 3) correction matrix; ``b0``: (3,) bias at ``T_ref_C`` in raw units;
    ``k``: (3,) bias temperature coefficient per degC. ``details`` holds
    uncertainties (``sigma_M``, ``sigma_b0``, ``sigma_k`` of the same shapes),
    covariances and fit statistics, JSON-serialisable.
    """

    sensor: str
    M: np.ndarray
    b0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    k: np.ndarray = field(default_factory=lambda: np.zeros(3))
    T_ref_C: float = T_REF_C
    solver: str = ""
    details: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.sensor not in SENSORS:
            raise SchemaError(f"unknown sensor {self.sensor!r}; expected one of {', '.join(SENSORS)}")
        for name, shape in (("M", (3, 3)), ("b0", (3,)), ("k", (3,))):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != shape:
                raise SchemaError(f"{self.sensor}.{name} has shape {value.shape}, expected {shape}")
            object.__setattr__(self, name, value)

    @property
    def S(self) -> np.ndarray:
        """(3, 3) forward scale/misalignment matrix, ``inv(M)``."""
        return np.linalg.inv(self.M)

    def bias(self, T: np.ndarray | float | None = None) -> np.ndarray:
        """Bias at temperature ``T`` (degC): (3,) or (n, 3)."""
        if T is None:
            return self.b0
        dT = np.asarray(T, dtype=float) - self.T_ref_C
        return self.b0 + np.multiply.outer(dT, self.k)

    def apply(self, y: np.ndarray, T: np.ndarray | float | None = None) -> np.ndarray:
        """Correct raw readings ``y`` (n, 3) to the instrument frame."""
        y = np.asarray(y, dtype=float)
        return (y - self.bias(T)) @ self.M.T

    def predict(self, x: np.ndarray, T: np.ndarray | float | None = None) -> np.ndarray:
        """Raw readings (n, 3) the model predicts for true inputs ``x`` (n, 3)."""
        x = np.asarray(x, dtype=float)
        return x @ self.S.T + self.bias(T)

    def to_dict(self) -> dict[str, Any]:
        return {
            "M": self.M.tolist(), "b0": self.b0.tolist(), "k": self.k.tolist(),
            "units": UNITS[self.sensor], "solver": self.solver, **_jsonable(dict(self.details)),
        }

    @classmethod
    def from_dict(cls, sensor: str, d: Mapping[str, Any], T_ref_C: float = T_REF_C) -> TriadCalibration:
        if d.get("units", UNITS[sensor]) != UNITS[sensor]:
            raise SchemaError(f"{sensor} calibration is in {d['units']!r}; imupipe expects {UNITS[sensor]!r}")
        details = {k: v for k, v in d.items() if k not in ("M", "b0", "k", "units", "solver")}
        return cls(sensor, np.array(d["M"]), np.array(d.get("b0", [0.0] * 3)), np.array(d.get("k", [0.0] * 3)),
                   T_ref_C, d.get("solver", ""), details)


@dataclass(frozen=True)
class Calibration:
    """The calibration of a session: one ``TriadCalibration`` per triad present."""

    triads: Mapping[str, TriadCalibration]
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __getitem__(self, sensor: str) -> TriadCalibration:
        try:
            return self.triads[sensor]
        except KeyError:
            raise SchemaError(f"no {sensor} calibration; this one has {', '.join(self.triads) or 'none'}") from None

    @property
    def model_terms(self) -> list[dict[str, Any]]:
        """The extra terms ``imupipe diagnose`` accepted: ``{"effect", "sensor", "parameters"}``
        (effects.md names, SI units, the calibration's frame). A term of the ``temperature``
        sensor (a thermal lag) acts on every triad, along its own ``k``."""
        return list(self.meta.get("model_terms", []))

    def predict(self, sensor: str, x: np.ndarray, T: np.ndarray | float | None = None,
                signals: Mapping[str, Any] | None = None) -> np.ndarray:
        """Raw readings (n, 3) of ``sensor`` for true inputs ``x`` (n, 3): the triad's model plus
        every model term of that sensor. ``signals``: what the terms need, by the names of the
        effects' ``regressors`` (``omega``, ``alpha`` rad/s, rad/s^2 for a lever arm; ``f_dot``
        m/s^3 for a time offset; ``f`` m/s^2 for a gyro g-sensitivity; ``t_on`` s for a warm-up;
        ``north``/``up`` unit vectors for Earth's rate; ``T_rate`` degC/s, the read-out's rate, for
        a thermal lag, along the triad's own ``k``); a missing one is a ``ConfigError``."""
        triad = self[sensor]
        x = np.asarray(x, dtype=float)
        return triad.predict(x, T) + self._terms(sensor, x @ triad.S.T, x, T, signals)

    def apply(self, sensor: str, y: np.ndarray, T: np.ndarray | float | None = None,
              signals: Mapping[str, Any] | None = None) -> np.ndarray:
        """Correct raw readings ``y`` (n, 3) of ``sensor`` with the triad's model and its model
        terms (subtracted first; evaluated at the nominal correction, exact to first order)."""
        triad = self[sensor]
        y = np.asarray(y, dtype=float)
        return triad.apply(y - self._terms(sensor, y - triad.bias(T), triad.apply(y, T), T, signals), T)

    def _terms(self, sensor: str, sensed: np.ndarray, x: np.ndarray, T, signals) -> np.ndarray | float:
        terms = [t for t in self.model_terms if t.get("sensor") in (sensor, "temperature")]
        if not terms:
            return 0.0
        from .plugins import make_registry  # the effects are plugins: loaded only when a term is applied

        registry = make_registry()
        inputs: dict[str, Any] = {"x": sensed}
        if T is not None:
            inputs["T"] = np.broadcast_to(np.asarray(T, dtype=float), (len(sensed),))
        if sensor == "accel":
            inputs["f"] = x
        inputs["k"] = self[sensor].k
        inputs.update(signals or {})
        return sum(registry.get("effects", t["effect"]).term(inputs, t["parameters"], self[sensor].S)
                   for t in terms)

    def to_dict(self) -> dict[str, Any]:
        """The ``calibration.json`` of ``spec/contracts.md`` (extra keys allowed)."""
        T_ref = next(iter(self.triads.values())).T_ref_C if self.triads else T_REF_C
        out: dict[str, Any] = {"format_version": FORMAT_VERSION, **_jsonable(dict(self.meta))}
        for sensor in SENSORS:
            if sensor in self.triads:
                out[sensor] = self.triads[sensor].to_dict()
        out["temperature_reference_C"] = T_ref
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Calibration:
        version = d.get("format_version", FORMAT_VERSION)
        if version > FORMAT_VERSION:
            raise SchemaError(f"calibration format version {version} is newer than this imupipe ({FORMAT_VERSION})")
        T_ref = float(d.get("temperature_reference_C", T_REF_C))
        triads = {s: TriadCalibration.from_dict(s, d[s], T_ref) for s in SENSORS if s in d}
        meta = {k: v for k, v in d.items() if k not in (*SENSORS, "temperature_reference_C", "format_version")}
        return cls(triads, meta)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2) + "\n"

    @classmethod
    def from_json(cls, text: str) -> Calibration:
        return cls.from_dict(json.loads(text))

    def to_table(self) -> pa.Table:
        return triads_to_table(list(self.triads.values()))

    @classmethod
    def from_tables(cls, *tables: pa.Table, meta: Mapping[str, Any] | None = None) -> Calibration:
        """Merge calibration tables (later rows of the same sensor win)."""
        triads: dict[str, TriadCalibration] = {}
        for table in tables:
            for t in triads_from_table(table):
                triads[t.sensor] = t
        return cls(triads, dict(meta or {}))


def triads_to_table(triads: list[TriadCalibration]) -> pa.Table:
    """A table of schema ``calibration``, one row per triad."""
    columns = {
        "sensor": [t.sensor for t in triads],
        "M": [t.M.ravel().tolist() for t in triads],
        "b0": [t.b0.tolist() for t in triads],
        "k": [t.k.tolist() for t in triads],
        "T_ref_C": [float(t.T_ref_C) for t in triads],
        "solver": [t.solver for t in triads],
        "details": [json.dumps(_jsonable(dict(t.details))) for t in triads],
    }
    target = schemas.arrow_schema("calibration")  # built in its types: no cast (pyarrow.compute)
    return schemas.stamp(pa.table({k: pa.array(v, type=target.field(k).type) for k, v in columns.items()}),
                         "calibration")


def triads_from_table(table: pa.Table) -> list[TriadCalibration]:
    schemas.check(table, "calibration")
    rows = table.to_pylist()
    return [
        TriadCalibration(r["sensor"], np.reshape(r["M"], (3, 3)), np.array(r["b0"]), np.array(r["k"]),
                         r["T_ref_C"], r["solver"], json.loads(r["details"]))
        for r in rows
    ]


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):  # numpy scalars, np.bool_ included
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj

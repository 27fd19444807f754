"""What calibrate stages hand to solvers: rests, turns and per-kind observation sets.

Built from the ``rests`` and ``turns`` tables of the stillness segmentation
(``stages/segment.py``). Solvers of both methods take these same types, so any
solver of a kind can replace another in config.

Units are SI throughout: time in s, accel m/s^2, gyro rad/s, mag T, temperature
degC. "raw" means in the sensor's own axes, before correction.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa

from .columns import vectors
from .errors import SolverError

TRIADS = ("accel", "gyro", "mag")


# --------------------------------------------------------------------------- rests / turns


@dataclass(frozen=True)
class Rests:
    """Stationary intervals, one row per rest, in time order.

    ``t_start_s``/``t_end_s``: (n,) s since the session's first sample;
    ``count``: (n,) accel sample count; ``counts[sensor]``: (n,) per triad;
    ``mean[sensor]``: (n, 3) mean raw reading; ``cov[sensor]``: (n, 3, 3)
    covariance of ONE sample (divide by ``counts`` for the mean's covariance);
    ``temperature``: (n,) mean degC, NaN when the session has none.
    ``t0_ns``: the session's first sample time (int ns) the seconds refer to.
    """

    t_start_s: np.ndarray
    t_end_s: np.ndarray
    count: np.ndarray
    mean: Mapping[str, np.ndarray]
    cov: Mapping[str, np.ndarray]
    temperature: np.ndarray
    counts: Mapping[str, np.ndarray] = field(default_factory=dict)
    t0_ns: int = 0

    def __len__(self) -> int:
        return len(self.t_start_s)

    @property
    def sensors(self) -> tuple[str, ...]:
        return tuple(s for s in TRIADS if s in self.mean)

    def has(self, sensor: str) -> bool:
        return sensor in self.mean

    def need(self, sensor: str) -> np.ndarray:
        """(n, 3) means of ``sensor`` or a SolverError saying it is missing."""
        if sensor not in self.mean:
            raise SolverError(
                f"the rests hold no {sensor} data (have: {', '.join(self.sensors) or 'none'}); "
                f"wire a session with a {sensor} stream into the segmentation stage"
            )
        return self.mean[sensor]

    def cov_of_mean(self, sensor: str) -> np.ndarray:
        """(n, 3, 3) covariance of each rest's mean reading."""
        n = np.maximum(self.counts.get(sensor, self.count), 1).astype(float)
        return self.cov[sensor] / n[:, None, None]

    def white_sigma(self, sensor: str) -> np.ndarray:
        """(3,) white-noise sigma of one sample per axis: median over rests (robust to a bad rest)."""
        return np.sqrt(np.median(np.diagonal(self.cov[sensor], axis1=1, axis2=2), axis=0))

    def subset(self, index: np.ndarray) -> Rests:
        """The rests at ``index`` (bool mask or integer array), same order."""
        index = np.asarray(index)
        return Rests(
            self.t_start_s[index], self.t_end_s[index], self.count[index],
            {s: v[index] for s, v in self.mean.items()}, {s: v[index] for s, v in self.cov.items()},
            self.temperature[index], {s: v[index] for s, v in self.counts.items()}, self.t0_ns,
        )

    # ----------------------------------------------------------------- Arrow
    @classmethod
    def from_table(cls, table: pa.Table) -> Rests:
        """From a ``rests`` table (schemas/rests.json); triads without columns are absent."""
        cols = set(table.column_names)
        n = table.num_rows

        def arr(name: str, width: int | None = None) -> np.ndarray:
            if width is None:
                return table.column(name).combine_chunks().to_numpy(zero_copy_only=False).astype(float)
            return vectors(table, name).astype(float).reshape(n, width)

        mean, cov, counts = {}, {}, {}
        for s in TRIADS:
            if f"{s}_mean" in cols:
                mean[s] = arr(f"{s}_mean", 3)
                cov[s] = arr(f"{s}_cov", 9).reshape(n, 3, 3)
                counts[s] = arr(f"{s}_count").astype(np.int64) if f"{s}_count" in cols \
                    else arr("count").astype(np.int64)
        meta = table.schema.metadata or {}
        t0 = int(meta.get(b"imupipe.t0_ns", b"0"))
        return cls(
            arr("t_start_s"), arr("t_end_s"), arr("count").astype(np.int64), mean, cov,
            arr("temperature"), counts, t0,
        )

    def to_table(self) -> pa.Table:
        """A ``rests`` table (stamped)."""
        from . import schemas

        n = len(self)
        data: dict[str, Any] = {
            "index": np.arange(n, dtype=np.int64),
            "t_start_ns": self.t0_ns + np.round(self.t_start_s * 1e9).astype(np.int64),
            "t_end_ns": self.t0_ns + np.round(self.t_end_s * 1e9).astype(np.int64),
            "t_start_s": self.t_start_s, "t_end_s": self.t_end_s,
            "count": self.count.astype(np.int64), "temperature": self.temperature,
        }
        for s in self.sensors:
            data[f"{s}_mean"] = pa.array(list(self.mean[s]), type=pa.list_(pa.float64(), 3))
            data[f"{s}_cov"] = pa.array(list(self.cov[s].reshape(n, 9)), type=pa.list_(pa.float64(), 9))
            data[f"{s}_count"] = self.counts.get(s, self.count).astype(np.int64)
        return schemas.stamp(pa.table(data), "rests", {"imupipe.t0_ns": str(int(self.t0_ns))})


@dataclass(frozen=True)
class Turns:
    """Motions between consecutive rests, one per turn.

    ``before``/``after``: (m,) int indices into ``Rests``; ``t``: m arrays (k_i,)
    of gyro sample times in s (same clock as ``Rests``), covering the motion
    from the end of rest ``before`` to the start of rest ``after``; ``gyro``:
    m arrays (k_i, 3) of raw gyro samples in rad/s.
    """

    before: np.ndarray
    after: np.ndarray
    t: tuple[np.ndarray, ...]
    gyro: tuple[np.ndarray, ...]

    def __len__(self) -> int:
        return len(self.before)

    def subset(self, index: np.ndarray) -> Turns:
        idx = np.arange(len(self))[np.asarray(index)]
        return Turns(self.before[idx], self.after[idx],
                     tuple(self.t[i] for i in idx), tuple(self.gyro[i] for i in idx))

    @classmethod
    def from_tables(cls, turns: pa.Table, gyro: pa.Table, t0_ns: int | None = None) -> Turns:
        """From a ``turns`` table and the session's raw ``gyro`` table.

        Each turn takes the gyro samples with ``t_start_ns <= t_ns <= t_end_ns``;
        times are seconds since ``t0_ns`` (default: the turns table's metadata).
        """
        if t0_ns is None:
            t0_ns = int((turns.schema.metadata or {}).get(b"imupipe.t0_ns", b"0"))
        tg = gyro.column("t_ns").to_numpy()
        xyz = [gyro.column(c).to_numpy() for c in ("x", "y", "z")]
        starts = turns.column("t_start_ns").to_numpy()
        ends = turns.column("t_end_ns").to_numpy()
        i0, i1 = np.searchsorted(tg, starts, "left"), np.searchsorted(tg, ends, "right")
        # the turns' samples copied once, one after the other, and each turn a view of them (not
        # of the whole recording): the joint model's motion samples are these very arrays
        # (``MotionSamples.from_turns``), read-only so that no one changes them for the other
        take = np.concatenate([np.arange(a, b) for a, b in zip(i0, i1, strict=True)] + [np.zeros(0, np.int64)])
        t_all = (tg[take] - t0_ns) * 1e-9
        w_all = np.empty((len(take), 3))
        for k, x in enumerate(xyz):
            w_all[:, k] = x[take]
        t_all.flags.writeable = w_all.flags.writeable = False
        edges = np.r_[0, np.cumsum(i1 - i0)]
        return cls(turns.column("rest_before").to_numpy().astype(np.int64),
                   turns.column("rest_after").to_numpy().astype(np.int64),
                   tuple(t_all[a:b] for a, b in itertools.pairwise(edges)),
                   tuple(w_all[a:b] for a, b in itertools.pairwise(edges)))


# --------------------------------------------------------------------------- solver inputs


@dataclass(frozen=True)
class ThermalObservations:
    """A warm-up at rest: ``t_s`` (n,) s, ``T`` (n,) degC, ``y`` (n, 3) raw
    averages (e.g. 1 s) in sensor units, ``sigma`` (3,) noise of one average.
    ``sensor``: accel | gyro | mag. ``T_ref_C``: the model's reference (25)."""

    sensor: str
    t_s: np.ndarray
    T: np.ndarray
    y: np.ndarray
    sigma: np.ndarray
    T_ref_C: float = 25.0


@dataclass(frozen=True)
class ThermalFit:
    """``b0`` (3,) bias at T_ref (meaningful for gyro only), ``k`` (3,) per degC,
    ``cov`` (6, 6) covariance of (b0, k); ``details`` JSON-able extras."""

    b0: np.ndarray
    k: np.ndarray
    cov: np.ndarray
    details: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class EllipsoidObservations:
    """Static readings of a constant-magnitude vector (gravity or the earth field).

    ``y`` (n, 3) raw rest means with the thermal bias already removed
    (``y - k (T - 25)``), ``cov`` (n, 3, 3) covariance of each mean,
    ``T`` (n,) degC (NaN if unknown), ``magnitude`` the vector's length in SI
    (g in m/s^2; the field in T, or 1.0 for a normalised field).
    Reference positions (accelerometer, eqs. 17-19): ``y_up`` / ``x_up`` rest
    indices where instrument Y / X points up, or None.
    Magnetometer (eqs. 21-25): ``gravity`` (n, 3) corrected unit specific force
    in the instrument frame for the same rests, ``dip_rad`` the dip angle
    (positive down) or None to estimate it.
    """

    sensor: str
    y: np.ndarray
    cov: np.ndarray
    T: np.ndarray
    magnitude: float = 1.0
    y_up: int | None = None
    x_up: int | None = None
    gravity: np.ndarray | None = None
    dip_rad: float | None = None


# The brief's names for the accel and mag inputs: both are ellipsoid observations.
AccelObservations = EllipsoidObservations
MagObservations = EllipsoidObservations


@dataclass(frozen=True)
class GyroObservations:
    """Rests and the turns between them, for the gyroscope.

    ``gravity`` (n, 3) corrected unit specific force at every rest (instrument
    frame, from the accelerometer calibration); ``bias`` (n, 3) raw gyro mean
    at every rest, rad/s; ``bias_cov`` (n, 3, 3) covariance of those means;
    ``turns``: the raw gyro during each motion (rests and turns with the thermal
    bias ``k (T - 25)`` already removed when it is known, so the ``b0`` a solver
    returns is the bias at 25 degC); ``roll_turn``: index into
    ``turns`` of the paper's scale turn (eq. 37), or None to scale from all.
    Optional noise model: ``gravity_cov`` (n, 3, 3) covariance of each unit
    gravity; ``rate_sigma`` (3,) white noise of one gyro sample, rad/s.
    """

    gravity: np.ndarray
    bias: np.ndarray
    bias_cov: np.ndarray
    turns: Turns
    T: np.ndarray | None = None
    roll_turn: int | None = None
    gravity_cov: np.ndarray | None = None
    rate_sigma: np.ndarray | None = None


@dataclass(frozen=True)
class TriadFit:
    """A solver's answer for one triad.

    ``M`` (3, 3) correction, ``b0`` (3,) bias in raw units, ``cov`` (12, 12)
    covariance of ``(M.ravel(), b0)`` (NaN where the method gives none),
    ``details`` JSON-able extras (fit statistics, intermediate quantities).
    """

    M: np.ndarray
    b0: np.ndarray
    cov: np.ndarray
    details: Mapping[str, Any] = field(default_factory=dict)

    def uncertainty(self) -> dict[str, Any]:
        """``sigma_M`` (3, 3), ``sigma_b0`` (3,) and the full ``covariance`` for ``details``."""
        sd = np.sqrt(np.clip(np.diag(self.cov), 0, None))
        return {"sigma_M": sd[:9].reshape(3, 3).tolist(), "sigma_b0": sd[9:12].tolist(),
                "covariance": np.asarray(self.cov).tolist(),
                "covariance_order": "M row-major (9), b0 (3)"}

    def to_calibration(self, sensor: str, solver: str, k: np.ndarray | None = None,
                       sigma_k: np.ndarray | None = None, extra: Mapping[str, Any] | None = None):
        """A ``models.TriadCalibration`` carrying the uncertainties in ``details``."""
        from .models import TriadCalibration

        details = {**self.uncertainty(), **dict(self.details), **dict(extra or {})}
        details["sigma_k"] = (np.zeros(3) if sigma_k is None else np.asarray(sigma_k)).tolist()
        return TriadCalibration(sensor, self.M, self.b0, np.zeros(3) if k is None else k,
                                solver=solver, details=details)


def forward_jacobian(cal: Any, x: np.ndarray, T: np.ndarray | float | None = None) -> np.ndarray:
    """(n, 3, 15) Jacobian of ``cal.predict(x, T)`` (the raw reading) with respect to the
    parameters ``(vec M row-major (9), b0 (3), k (3))`` of a ``models.TriadCalibration``.

    ``y = S x + b0 + k (T - T_ref)`` with ``S = M^-1``, so ``dy/dM_ij = -S[:, i] (S x)_j``.
    ``x`` (n, 3) true inputs in the instrument frame; ``T`` (n,) degC or None (no thermal term).
    """
    x = np.atleast_2d(np.asarray(x, dtype=float))
    S = np.linalg.inv(cal.M)
    Sx = x @ S.T
    n = len(x)
    J = np.zeros((n, 3, 15))
    J[:, :, :9] = -np.einsum("ai,nj->naij", S, Sx).reshape(n, 3, 9)
    J[:, :, 9:12] = np.eye(3)
    if T is not None:
        dT = np.broadcast_to(np.asarray(T, dtype=float) - cal.T_ref_C, (n,))
        J[:, :, 12:15] = dT[:, None, None] * np.eye(3)
    return J

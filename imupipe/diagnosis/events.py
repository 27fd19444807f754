"""Find the events a model must not be fitted across: gaps, one-sample shocks, splices.

One place for these detectors: the ``screen_events`` stage runs them before any fit
(turns that hold one are left out), the residual map receives their table (its
``events``), the verdict counts them.

- **gap**: consecutive stamps further apart than ``gap_factor`` nominal intervals (and
  ``gap_min_s``): whatever the unit did meanwhile was not measured;
- **shock**: one sample far from both neighbours, which agree with each other (a knock:
  several g, hundreds of deg/s, for one sample);
- **splice**: the accelerometer's gravity direction jumps between two consecutive samples,
  from one quiet stretch to another, by more than the gyro's measured rotation around them
  can explain (a recording made of sections joined together);
- **saturation**: gyro samples held at the triad's full scale (``clipped``): the rotation
  beyond it was not measured, so no model of the gyro can be integrated across them.

Times are seconds from the session's first sample (``t0_ns``), as the rests' clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Event:
    """Something the model must not be fitted across: ``kind`` (shock, gap, splice, saturation,
    translation, change_point, ...), ``sensor``, ``window`` (t0, t1) s, ``detail`` one line."""

    kind: str
    sensor: str
    window: tuple[float, float]
    detail: str

    def to_dict(self) -> dict:
        return {"kind": self.kind, "sensor": self.sensor, "window": [float(self.window[0]), float(self.window[1])],
                "detail": self.detail}


GAP_FACTOR = 3.0  # a stamp interval this many times the nominal one is a gap
GAP_MIN_S = 0.05
SHOCK_ACCEL_M_S2 = 9.80665  # a sample this far from both neighbours (1 g) is a knock
SHOCK_GYRO_RAD_S = 1.0  # 57 deg/s in one sample
SPLICE_MIN_DEG = 5.0  # gravity jumps smaller than this are not judged
SPLICE_WINDOW = 10  # samples each side whose median gives the directions before and after
STEP_CLEAN = 0.2  # each side stays within this fraction of the jump of its median (quiet)
MIN_RAIL_RUN = 2  # consecutive samples at a rail that mean clipping
SATURATION_JOIN_S = 0.5  # clipped runs closer than this are one event


def nominal_interval(t_s: np.ndarray) -> float:
    """The stamp interval of a stream, s: the larger of the median and the mean (bursty stamps)."""
    dt = np.diff(t_s)
    return float(max(np.median(dt), (t_s[-1] - t_s[0]) / max(len(dt), 1))) if len(dt) else float("nan")


def find_gaps(t_s: np.ndarray, sensor: str, factor: float = GAP_FACTOR, min_s: float = GAP_MIN_S
              ) -> list[Event]:
    """Gaps in the stamps ``t_s`` (k,) s of one stream."""
    if len(t_s) < 3:
        return []
    nominal = nominal_interval(t_s)
    dt = np.diff(t_s)
    out = []
    for i in np.flatnonzero(dt > max(factor * nominal, min_s)):
        out.append(Event("gap", sensor, (float(t_s[i]), float(t_s[i + 1])),
                         f"{sensor}: no samples for {dt[i]:.3g} s ({dt[i] / nominal:.0f} intervals) "
                         f"after {t_s[i]:.2f} s"))
    return out


def find_shocks(t_s: np.ndarray, y: np.ndarray, sensor: str, threshold: float) -> list[Event]:
    """One-sample spikes of ``y`` (k, 3): away from both neighbours by more than ``threshold``
    (raw units) while the neighbours agree within half of that."""
    if len(t_s) < 3:
        return []
    prev, here, nxt = y[:-2], y[1:-1], y[2:]
    away = np.minimum(np.linalg.norm(here - prev, axis=1), np.linalg.norm(here - nxt, axis=1))
    agree = np.linalg.norm(nxt - prev, axis=1)
    hit = np.flatnonzero((away > threshold) & (agree < 0.5 * away)) + 1
    unit = "m/s^2" if sensor == "accel" else "rad/s" if sensor == "gyro" else "raw units"
    out = []
    for i in hit:
        size = float(np.linalg.norm(y[i] - 0.5 * (y[i - 1] + y[i + 1])))
        out.append(Event("shock", sensor, (float(t_s[i - 1]), float(t_s[i + 1])),
                         f"{sensor}: one sample at {t_s[i]:.3f} s is {size:.3g} {unit} away from both "
                         "neighbours (a knock)"))
    return out


def find_splices(t_a: np.ndarray, a: np.ndarray, t_g: np.ndarray, w: np.ndarray,
                 min_deg: float = SPLICE_MIN_DEG, window: int = SPLICE_WINDOW) -> list[Event]:
    """Jumps of the gravity direction between consecutive accelerometer samples that the gyro
    does not explain: the direction before (median of ``window`` samples) and after differ by
    more than ``min_deg`` and by more than twice the rotation the gyro integrates (sum of
    ``|omega| dt``, an upper bound) over the same stretch, plus ``min_deg``."""
    k = len(t_a)
    if k < 2 * window + 2 or len(t_g) < 2:
        return []
    step = np.linalg.norm(np.diff(a, axis=0), axis=1)
    g = float(np.median(np.linalg.norm(a, axis=1)))
    candidates = np.flatnonzero(step > 2 * g * np.sin(np.radians(min_deg) / 2))
    dt_g = np.diff(t_g, append=t_g[-1])
    rot = np.concatenate([[0.0], np.cumsum(np.linalg.norm(w, axis=1) * dt_g)])
    out: list[Event] = []
    last = -np.inf
    for i in candidates:  # the jump is between samples i and i + 1
        if i < window - 1 or i + 1 + window > k or t_a[i] <= last:
            continue
        u0 = np.median(a[i + 1 - window:i + 1], axis=0)
        u1 = np.median(a[i + 1:i + 1 + window], axis=0)
        n0, n1 = np.linalg.norm(u0), np.linalg.norm(u1)
        if n0 == 0 or n1 == 0:
            continue
        spread = max(np.linalg.norm(a[i + 1 - window:i + 1] - u0, axis=1).max(),
                     np.linalg.norm(a[i + 1:i + 1 + window] - u1, axis=1).max())
        if spread > STEP_CLEAN * np.linalg.norm(u1 - u0):
            continue  # not a clean step between two quiet stretches: motion, not a splice
        jump = float(np.degrees(np.arccos(np.clip(u0 @ u1 / (n0 * n1), -1, 1))))
        j0 = np.searchsorted(t_g, t_a[i + 1 - window], "left")
        j1 = np.searchsorted(t_g, t_a[i + window], "right")
        turned = float(np.degrees(rot[j1] - rot[j0]))
        if jump > min_deg and jump > 2 * turned + min_deg:
            last = float(t_a[i + window])
            out.append(Event("splice", "accel", (float(t_a[i]), float(t_a[i + 1])),
                             f"gravity jumps {jump:.0f} deg between the samples at {t_a[i]:.3f} and "
                             f"{t_a[i + 1]:.3f} s while the gyro measures {turned:.2g} deg of rotation "
                             "(sections of recordings joined together?)"))
    return out


def clipped(w: np.ndarray, limit: float | None = None) -> np.ndarray:
    """(k, 3) bool: the samples of ``w`` (k, 3) held at the full scale.

    With ``limit`` a sample is clipped when ``|w| >= limit``. Otherwise a rail is an axis's
    largest or smallest value, held for ``MIN_RAIL_RUN`` or more consecutive samples, whose
    magnitude is also the rail of another axis or sign: the triad's common full scale. (A
    single axis resting at its extreme is a constant-rate turn, not clipping.)"""
    if limit is not None:
        return np.abs(w) >= limit
    flag = np.zeros(w.shape, bool)
    if not len(w):
        return flag
    rails = []  # (axis, value, run mask)
    for ax in range(3):
        for rail in (w[:, ax].max(), w[:, ax].min()):
            at = np.abs(w[:, ax] - rail) <= 1e-9 * max(abs(rail), 1e-300)
            edges = np.diff(np.concatenate([[0], at.astype(np.int8), [0]]))
            run = np.zeros(len(w), bool)
            for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
                if b - a >= MIN_RAIL_RUN:
                    run[a:b] = True
            if run.any() and rail != 0:
                rails.append((ax, rail, run))
    for i, (ax, rail, run) in enumerate(rails):
        if any(j != i and abs(abs(r) - abs(rail)) <= 1e-6 * abs(rail) for j, (_, r, _) in enumerate(rails)):
            flag[:, ax] |= run
    return flag


def find_saturation(t_s: np.ndarray, w: np.ndarray, sensor: str = "gyro") -> list[Event]:
    """Stretches where ``w`` (k, 3) sits on the rails of its full scale (``clipped``), runs
    closer than ``SATURATION_JOIN_S`` joined."""
    hit = np.flatnonzero(clipped(w).any(axis=1))
    if not len(hit):
        return []
    cuts = np.flatnonzero(np.diff(t_s[hit]) > SATURATION_JOIN_S)
    out = []
    for a, b in zip(np.r_[0, cuts + 1], np.r_[cuts, len(hit) - 1], strict=True):
        i0, i1 = hit[a], hit[b]
        top = float(np.abs(w[hit[a:b + 1]]).max())
        out.append(Event("saturation", sensor, (float(t_s[i0]), float(t_s[i1])),
                         f"{sensor}: samples clipped at {top:.4g} (the full scale) between {t_s[i0]:.2f} "
                         f"and {t_s[i1]:.2f} s: the rotation beyond it was not measured"))
    return out


def detect(streams: dict[str, tuple[np.ndarray, np.ndarray]], *, gap_factor: float = GAP_FACTOR,
           gap_min_s: float = GAP_MIN_S, shock: dict[str, float] | None = None,
           splice_min_deg: float = SPLICE_MIN_DEG) -> list[Event]:
    """Every event of a session, sorted by time: ``streams`` ``{"accel": (t (k,) s, y (k, 3)),
    "gyro": ...}`` raw, seconds from the session's first sample; ``shock``: sensor -> threshold
    in its raw unit (default: accel and gyro in SI); splices need accel and gyro."""
    shock = {"accel": SHOCK_ACCEL_M_S2, "gyro": SHOCK_GYRO_RAD_S} if shock is None else shock
    events: list[Event] = []
    for sensor, (t, y) in streams.items():
        events += find_gaps(t, sensor, gap_factor, gap_min_s)
        if sensor in shock:
            events += find_shocks(t, y, sensor, shock[sensor])
    if "gyro" in streams:
        events += find_saturation(*streams["gyro"])
    if "accel" in streams and "gyro" in streams:
        events += find_splices(*streams["accel"], *streams["gyro"], min_deg=splice_min_deg)
    return sorted(events, key=lambda e: e.window[0])

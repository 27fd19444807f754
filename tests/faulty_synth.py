"""Faulty recordings built from a clean simulated one: the silent-wrong cases of issues 10 and 12.

Each function takes the columns of a canonical CSV (``imupipe.sim.api.CSV_COLUMNS``, as a
dict of numpy arrays) and returns new columns: sections spliced together, a gap inside a
motion, a one-sample shock inside a motion, a stream in another unit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imupipe.sim.api import CSV_COLUMNS, simulate_recording, write_csv

G = 9.80665


def clean_gimbal(path: Path, seed: int = 4) -> dict[str, np.ndarray]:
    """A short gimbal session (60-deg grid, 12 rotations, 3.5-s rests) written to ``path``."""
    rec, _ = simulate_recording("gimbal", {}, seed, grid_deg=60.0, n_rotations=12, rest_s=3.5)
    write_csv(path, rec)
    return read(path)


def read(path: Path) -> dict[str, np.ndarray]:
    import polars as pl

    df = pl.read_csv(path)
    return {c: df[c].to_numpy() for c in df.columns}


def write(path: Path, cols: dict[str, np.ndarray]) -> Path:
    import polars as pl

    pl.DataFrame({c: cols[c] for c in CSV_COLUMNS}).write_csv(path, float_precision=None)
    return path


def rate(cols) -> np.ndarray:
    return np.linalg.norm(np.column_stack([cols[f"gyro_{a}"] for a in "xyz"]), axis=1)


def motions(cols, threshold: float = 0.2) -> list[tuple[int, int]]:
    """Index ranges [i0, i1) where the unit turns faster than ``threshold`` rad/s."""
    moving = np.r_[False, rate(cols) > threshold, False].astype(np.int8)
    edges = np.diff(moving)
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def tilting(cols, n: int = 1) -> list[int]:
    """The ``n`` longest motions among those tilting gravity by more than 30 deg: a turn about
    the vertical is invisible to the gravity the gyro is fitted on."""
    a = np.column_stack([cols[f"accel_{x}"] for x in "xyz"])
    scored = []
    for j, (i0, i1) in enumerate(motions(cols)):
        u0, u1 = a[max(i0 - 20, 0):i0].mean(axis=0), a[i1:i1 + 20].mean(axis=0)
        tilt = np.degrees(np.arccos(np.clip(u0 @ u1 / np.linalg.norm(u0) / np.linalg.norm(u1), -1, 1)))
        if tilt > 30:
            scored.append((i1 - i0, j))
    return [j for _, j in sorted(scored, reverse=True)[:n]]


def splice(cols, n_cuts: int = 4) -> tuple[dict[str, np.ndarray], list[float]]:
    """Cut out ``n_cuts`` stretches, each from the middle of one rest to the middle of a rest
    several motions later (a different attitude), and join the rest with continuous stamps:
    gravity jumps between two consecutive samples with no rotation measured. Returns the columns
    and the times of the joins, s from the first sample."""
    ms = motions(cols)
    keep = np.ones(len(cols["t_ns"]), bool)
    joins: list[int] = []
    step = max(len(ms) // (n_cuts + 1), 2)
    for k in range(n_cuts):
        a, b = k * step + 1, k * step + 2  # cut from the rest before motion a to the rest after b
        if b >= len(ms) - 1:
            break
        i = (ms[a - 1][1] + ms[a][0]) // 2 if a else ms[0][0] // 2
        j = (ms[b][1] + ms[b + 1][0]) // 2
        keep[i:j] = False
        joins.append(int(i - (~keep[:i]).sum()))  # the join's index in the kept samples
    out = {c: v[keep] for c, v in cols.items()}
    dt = int(np.median(np.diff(cols["t_ns"])))
    out["t_ns"] = cols["t_ns"][0] + dt * np.arange(int(keep.sum()), dtype=np.int64)
    return out, [j * dt * 1e-9 for j in joins]


def gap(cols, n: int = 3, seconds: float = 0.8) -> tuple[dict[str, np.ndarray], list[float]]:
    """Drop ``seconds`` of samples early in each of the ``n`` ``tilting`` motions
    (stamps untouched: the samples are missing). Returns the columns and the gaps' starts, s."""
    t = (cols["t_ns"] - cols["t_ns"][0]) * 1e-9
    drop = np.zeros(len(t), bool)
    starts = []
    ms = motions(cols)
    for j in tilting(cols, n):
        i0, i1 = ms[j]
        start = t[i0] + 0.1 * (t[i1 - 1] - t[i0])  # on the ramp up: the held rate is not the lost one
        drop |= (t >= start) & (t < start + seconds)
        starts.append(float(start))
    return {c: v[~drop] for c, v in cols.items()}, sorted(starts)


def shock(cols, motion: int | None = None, g: float = 5.0, dps: float = 400.0) -> tuple[dict[str, np.ndarray], float]:
    """One sample in the middle of motion ``motion`` hit by ``g`` g on accel x and ``dps`` deg/s
    on gyro y (a knock; default: in the ``tilting`` motion). Returns the columns and the sample's
    time, s."""
    i0, i1 = motions(cols)[tilting(cols)[0] if motion is None else motion]
    i = (i0 + i1) // 2
    out = {c: v.copy() for c, v in cols.items()}
    out["accel_x"][i] += g * G
    out["gyro_y"][i] += np.radians(dps)
    return out, float((cols["t_ns"][i] - cols["t_ns"][0]) * 1e-9)


def units(cols, sensor: str, factor: float) -> dict[str, np.ndarray]:
    """``sensor``'s columns multiplied by ``factor`` (1/9.80665: g; 180/pi: deg/s; 1e6: uT)."""
    out = dict(cols)
    for a in "xyz":
        out[f"{sensor}_{a}"] = cols[f"{sensor}_{a}"] * factor
    return out


def fast_pipeline(folder: Path, pipelines: Path) -> Path:
    """``gimbal-optimization.toml`` without its residual-map stage (about 1 s of fitting):
    screening, method B's stages, the joint refinement and the control set."""
    text = (pipelines / "gimbal-optimization.toml").read_text()
    path = Path(folder) / "fast.toml"
    path.write_text(text.split("[stages.map]")[0] + '[export]\ncalibration = ["accel.calibration", '
                    '"gyro.calibration", "refine.calibration"]\nreports = ["control.control", "rests.rests"]\n')
    return path

"""Report section of the stillness segmentation: what it saw, and the time series with rests shaded."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa

from .spans import shade


def summary(table: pa.Table) -> dict:
    return json.loads((table.schema.metadata or {}).get(b"imupipe.segmentation", b"{}"))


def lines(table: pa.Table) -> list[str]:
    """Markdown: rests found, candidate holds and their lengths, noise floors and thresholds."""
    s = summary(table)
    if not s:
        return []
    p = s.get("params", {})
    out = ["## Stillness segmentation", "",
           f"{s['rests']} rests kept of {s['candidate_holds']} candidate holds "
           + (f"({s['hold_s_min']:.2f}-{s['hold_s_max']:.2f} s, median {s['hold_s_median']:.2f} s; "
              f"{s['holds_shorter_than_min_rest_s']} shorter than min_rest_s = {p.get('min_rest_s')} s); "
              if s["candidate_holds"] else "")
           + f"still {100 * s['still_fraction']:.0f} % of the time.", "",
           "| triad | noise floor (windowed variance) | threshold | factor |", "|---|---|---|---|"]
    for sensor, unit in (("accel", "(m/s^2)^2"), ("gyro", "(rad/s)^2")):
        out.append(f"| {sensor} | {s['noise_floor'][sensor]:.3g} {unit} | {s['threshold'][sensor]:.3g} | "
                   f"{p.get(sensor + '_threshold')} |")
    vib = s.get("vibration_ratio", {})
    out += ["", (f"Floor from {s['floor_from']}; window {p.get('window_s')} s, low-pass {p.get('lowpass_s')} s. "
                 + ("Holds tremble (hand-held or vibrating support): edges from the low-passed signals. "
                    if s.get("vibrating") else "")
                 + ("Short-mean spread over white noise's: "
                    + ", ".join(f"{k} {v:.2g}" for k, v in vib.items()) + "." if vib else "")), ""]
    return out


def draw(fig, table: pa.Table) -> None:
    """Accel (m/s^2) and gyro (deg/s) per axis along the session, rests shaded."""
    axes = fig.subplots(2, 1, sharex=True)
    t = table.column("t_s").to_numpy() / 60
    rest = table.column("rest").to_numpy(zero_copy_only=False).astype(bool)
    edges = np.flatnonzero(np.diff(np.r_[0, rest.astype(int), 0]))
    for ax, sensor, scale, unit in ((axes[0], "accel", 1.0, "m/s^2"), (axes[1], "gyro", 180 / np.pi, "deg/s")):
        shade(ax, t[edges[0::2]], t[edges[1::2] - 1], color="0.85", lw=0)
        for c in "xyz":
            ax.plot(t, table.column(f"{sensor}_{c}").to_numpy() * scale, lw=0.6, label=c)
        ax.set_ylabel(f"{sensor}, {unit}", fontsize=8)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        ax.grid(alpha=0.3)
    axes[1].set_xlabel("session time, min (rests shaded)")

"""Report section of the noise stage: the fitted terms and the Allan deviation plot."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa

LABELS = {"accel": ("m/s^2", 1.0), "gyro": ("deg/s", 180 / np.pi), "mag": ("uT", 1e6)}


def lines(noise: pa.Table) -> list[str]:
    """Markdown: per triad and axis, the five terms, in the triad's units."""
    doc = json.loads((noise.schema.metadata or {}).get(b"imupipe.noise", b"{}"))
    out = ["## Noise from the recording itself (Allan deviation)", "",
           f"Model: {doc.get('model', '')}; pooled over rests "
           + ", ".join(f"{r['index']} ({r['duration_s']:.0f} s)" for r in doc.get("rests_used", [])) + ".", "",
           "| triad | axis | rate Hz | noise density N /sqrt(Hz) | random walk K /s/sqrt(Hz) | bias instability B "
           "| quantisation Q *s | white sigma per sample | units |", "|---|---|---|---|---|---|---|---|---|"]
    for r in noise.to_pylist():
        out.append(f"| {r['sensor']} | {r['axis']} | {r['rate_hz']:.4g} | {r['noise_density']:.3g} | "
                   f"{r['random_walk']:.3g} | {r['bias_instability']:.3g} | {r['quantisation']:.3g} | "
                   f"{r['white_sigma']:.3g} | {r['units']} |")
    if "kalibr" in doc:
        out += ["", "Kalibr (largest axis): " + ", ".join(f"`{k}: {v:.4g}`" for k, v in doc["kalibr"].items()
                                                          if isinstance(v, float))]
    return [*out, ""]


def draw(fig, allan: pa.Table) -> None:
    """Log-log Allan deviation per triad (one panel each), per axis, with the fit."""
    sensor = np.asarray(allan.column("sensor").to_pylist())
    axis = np.asarray(allan.column("axis").to_pylist())
    present = [s for s in ("accel", "gyro", "mag") if (sensor == s).any()]
    axes = np.atleast_1d(fig.subplots(len(present), 1))
    for ax, s in zip(axes, present, strict=True):
        unit, scale = LABELS[s]
        for c in "xyz":
            m = (sensor == s) & (axis == c)
            tau = allan.column("tau_s").to_numpy()[m]
            ad, err = allan.column("adev").to_numpy()[m] * scale, allan.column("adev_err").to_numpy()[m] * scale
            line, = ax.loglog(tau, ad, ".", ms=4, label=f"{c}")
            ax.fill_between(tau, np.maximum(ad - err, ad * 0.1), ad + err, color=line.get_color(), alpha=0.15, lw=0)
            ax.loglog(tau, allan.column("adev_fit").to_numpy()[m] * scale, "-", color=line.get_color(), lw=1)
        ax.set_ylabel(f"{s} Allan dev., {unit}", fontsize=8)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    axes[-1].set_xlabel("averaging time tau, s (dots: measured, lines: fit)")

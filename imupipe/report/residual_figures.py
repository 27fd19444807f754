"""The residual map in the report: where the model fails, as a heat map and along the session.

``map_lines`` writes the markdown (blocks, the ranked cells, the events);
``draw_heat_map`` shows chi2/dof per cell for one sensor (rows: regime variable
and bin; columns: axes), ``draw_time_series`` the whitened residuals along the
session with the rests shaded and the flagged cells' windows marked.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from ..columns import equals, vectors
from .spans import shade

GRAVITY_CELLS = ("+x up", "-x up", "+y up", "-y up", "+z up", "-z up")


def _fmt_range(c: dict) -> str:
    lo, hi = c["range"]
    if isinstance(lo, str):
        return lo
    if lo is None and hi is None:
        return "all"
    lo_s = "-inf" if lo is None else f"{lo:.3g}"
    hi_s = "inf" if hi is None else f"{hi:.3g}"
    return f"[{lo_s}, {hi_s})"


def map_lines(doc: dict, top: int = 12) -> list[str]:
    """Markdown: the blocks' chi2/dof, the ranked cells, the events."""
    lines = ["## Residual map: where the calibrated model fails", "",
             "Every sample predicted under the calibration (rests, turns, every accelerometer sample "
             "inside the motions), whitened by the recording's own noise model; chi2/dof is 1 +- "
             "sqrt(2/dof) where the model holds. Cells are flagged by Benjamini-Hochberg at "
             f"q = {doc.get('fdr_q', 0.05)} across all {len(doc['cells'])} cells.", "",
             "| block | sensor | rows | chi2/dof (white noise only) | chi2/dof (own noise model) | dof |",
             "|---|---|---|---|---|---|"]
    for b in doc["blocks"]:
        white = b.get("chi2_per_dof_white")
        lines.append(f"| {b['block']} | {b['sensor']} | {b.get('rows', '')} | "
                     f"{'' if white is None else f'{white:.3g}'} | "
                     f"{'' if b['chi2_per_dof'] is None else format(b['chi2_per_dof'], '.3g')} | {b['dof']:.0f} |")
    flagged = [c for c in doc["cells"] if c["flagged"]]
    lines += ["", f"**{len(flagged)} cell(s) flagged.**" if flagged else
              "**No cell flagged**: the model explains the recording within its noise.", ""]
    lines += ["| rank | sensor | axes | regime | variable | range | chi2/dof | dof | p | flagged |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for c in doc["cells"][:top]:
        lines.append(f"| {c['rank']} | {c['sensor']} | {','.join(c['axes'])} | {c['regime']} | {c['variable']} | "
                     f"{_fmt_range(c)} | {c['chi2_per_dof']:.3g} | {c['dof']:.0f} | {c['p_value']:.2g} | "
                     f"{'yes' if c['flagged'] else ''} |")
    lines.append("")
    if doc["events"]:
        lines += ["Events:", ""] + [f"- {e['kind']} ({e['sensor']}) at {e['window'][0]:.1f}-{e['window'][1]:.1f} s: "
                                    f"{e['detail']}" for e in doc["events"]] + [""]
    else:
        lines += ["No events (gaps, shocks, splices, carries, change points).", ""]
    return lines


def draw_heat_map(fig, doc: dict, sensor: str) -> None:
    """chi2/dof per (variable, bin) row and axis column for one sensor, both regimes."""
    cells = [c for c in doc["cells"] if c["sensor"] == sensor and len(c["axes"]) == 1]
    keys = sorted({(c["regime"], c["variable"], _fmt_range(c)) for c in cells},
                  key=lambda k: (k[0], k[1], k[2]))
    M = np.full((len(keys), 3), np.nan)
    flag = np.zeros((len(keys), 3), bool)
    index = {k: i for i, k in enumerate(keys)}
    for c in cells:
        i = index[(c["regime"], c["variable"], _fmt_range(c))]
        j = "xyz".index(c["axes"][0])
        M[i, j] = c["chi2_per_dof"]
        flag[i, j] = c["flagged"]
    ax = fig.subplots(1, 1)
    if not len(keys):
        ax.text(0.5, 0.5, "no cells", ha="center")
        return
    im = ax.imshow(np.log10(np.clip(M, 1e-2, None)), aspect="auto", cmap="RdBu_r", vmin=-0.5, vmax=0.5)
    for i, j in zip(*np.nonzero(flag), strict=True):
        ax.text(j, i, "*", ha="center", va="center", color="k", fontsize=10)
    ax.set_xticks(range(3), ["x", "y", "z"])
    ax.set_yticks(range(len(keys)), [f"{r}: {v} {b}" for r, v, b in keys], fontsize=5)
    cb = fig.colorbar(im, ax=ax)
    cb.set_label("log10 chi2/dof (0 = the model holds)")


def draw_time_series(fig, samples: pa.Table, doc: dict, every: int = 5) -> None:
    """Whitened residual per sensor and axis along the session (every ``every``-th sample),
    rests shaded, flagged cells' windows in red, events as vertical lines."""
    axes = fig.subplots(2, 1, sharex=True)
    t = samples.column("t_s").to_numpy()
    rest_all = equals(samples, "kind", "rest")
    w = vectors(samples, "whitened")
    flagged = [c for c in doc["cells"] if c["flagged"]]
    for ax, s in zip(axes, ("accel", "gyro"), strict=True):
        m = equals(samples, "sensor", s)
        ts, ws, rest = t[m], w[m], rest_all[m]
        edges = np.flatnonzero(np.diff(np.r_[0, rest.astype(int), 0]))
        shade(ax, ts[edges[0::2]] / 60, ts[edges[1::2] - 1] / 60, color="0.9", lw=0)
        for i, c in enumerate("xyz"):
            ax.plot(ts[::every] / 60, ws[::every, i], ".", ms=1, alpha=0.5, label=c)
        windows = np.array([w for c in flagged if c["sensor"] == s for w in c["windows"]]).reshape(-1, 2)
        shade(ax, windows[:, 0] / 60, windows[:, 1] / 60, color="r", alpha=0.2, lw=0)
        for e in doc["events"]:
            if e["sensor"] in (s, "all"):
                ax.axvline(e["window"][0] / 60, color="m", lw=0.8)
        ax.set_ylim(-6, 6)
        ax.set_ylabel(f"{s} whitened\nresidual", fontsize=8)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0), markerscale=6)
        ax.grid(alpha=0.3)
    axes[1].set_xlabel("session time, min (rests shaded; flagged windows red; events magenta)")


def diagnosis_lines(doc: dict) -> list[str]:
    """The diagnosis in words: findings, effects this recording cannot see, effects not tested."""
    lines = ["## Diagnosis: physics the calibrated model leaves out", ""]
    if not doc["findings"]:
        lines += ["No finding: the calibrated model explains the recording (every catalogue effect tested "
                  f"at FDR q = {doc['fdr_q']}).", ""]
    for f in doc["findings"]:
        where = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in f["windows"][:4])
        lines += [f"- **{f['effect']}** ({f['sensor']}, {f['regime']}; {where}): {f['explanation']}"]
    if doc["not_identifiable"]:
        lines += ["", "Cannot be told apart from the nominal parameters on this recording:", ""]
        lines += [f"- {n['effect']} ({n['sensor']}): would bias {', '.join(n['biases'])}; "
                  f"reveal with {n['reveal_with']}" for n in doc["not_identifiable"]]
    if doc.get("untested"):
        lines += ["", "Not tested: " + "; ".join(f"{u['effect']} ({u['reason']})" for u in doc["untested"])]
    return lines + [""]


def draw_heldout(ax, findings: list[dict]) -> None:
    """Held-out RMS (sensor units) without and with each accepted term."""
    x = np.arange(len(findings))
    before = [f["heldout_rms_before"] for f in findings]
    after = [f["heldout_rms_after"] for f in findings]
    ax.bar(x - 0.2, before, 0.4, label="without the term")
    ax.bar(x + 0.2, after, 0.4, label="with the term")
    ax.set_xticks(x, [f"{f['effect']}\n({f['sensor']})" for f in findings], fontsize=8)
    ax.set_ylabel("held-out RMS, sensor units")
    ax.legend(fontsize=8)

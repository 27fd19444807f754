"""The ``report`` exporter: ``report.md`` with PNG figures of a run's residual and validation tables.

Tables are recognised by their schema, not by the pipeline's names for them:
``residuals`` (per stage: |g| and |B| errors before/after, the thermal fit, the
gyro's turn residuals), ``validation`` (turn-angle errors, eq. 39) and
``rests`` (positions on the sphere). Needs the ``report`` extra (matplotlib).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from .. import schemas
from ..errors import require
from ..io import atomic_path, write_text


def _col(table: pa.Table, name: str) -> np.ndarray:
    col = table.column(name).combine_chunks()
    if pa.types.is_fixed_size_list(col.type):
        return col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), -1)
    return col.to_numpy(zero_copy_only=False)


def _save(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")


def _by_stage(tables: Mapping[str, pa.Table]) -> dict[tuple[str, str, str], pa.Table]:
    """Residual rows grouped by (stage, sensor, kind)."""
    out: dict[tuple[str, str, str], pa.Table] = {}
    for t in tables.values():
        if schemas.schema_of(t) != "residuals":
            continue
        stage, sensor, kind = (_col(t, c) for c in ("stage", "sensor", "kind"))
        for key in sorted(set(zip(stage, sensor, kind, strict=True))):
            mask = (stage == key[0]) & (sensor == key[1]) & (kind == key[2])
            out[key] = t.filter(pa.array(mask))
    return out


class ReportExporter:
    """Writes ``out_dir/report.md`` and ``out_dir/figures/*.png``."""

    name = "report"

    def export(self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path) -> list[Path]:
        mpl = require("matplotlib", "report")
        mpl.use("Agg")
        import matplotlib.pyplot as plt

        out_dir = Path(out_dir)
        figs = out_dir / "figures"
        written: list[Path] = []
        lines = [f"# Calibration report: {context.get('session', '?')}", "",
                 f"pipeline `{context.get('pipeline', '?')}`, imupipe {context.get('imupipe_version', '?')}", ""]
        if context.get("skipped"):
            lines += ["Skipped stages: " + ", ".join(f"`{k}` ({v})" for k, v in dict(context["skipped"]).items()), ""]
        groups = _by_stage(results)

        def figure(name: str, title: str, draw) -> None:
            fig, ax = plt.subplots(figsize=(7, 3.6))
            draw(ax)
            ax.set_title(title)
            ax.grid(alpha=0.3)
            path = figs / f"{name}.png"
            _save(fig, path)
            plt.close(fig)
            written.append(path)
            lines.extend([f"![{title}](figures/{name}.png)", ""])

        for (stage, sensor, kind), t in groups.items():
            before, after = _col(t, "norm_error_before"), _col(t, "norm_error_after")
            if kind == "rest" and np.isfinite(after).any():
                ref = "g" if sensor == "accel" else "B"
                lines += [f"## {sensor}: |{ref}| error per rest ({stage})", "",
                          (f"RMS before {np.sqrt(np.nanmean(before**2)):.3g}, after "
                           f"{np.sqrt(np.nanmean(after**2)):.3g} (relative)"), ""]

                def draw(ax, before=before, after=after, ref=ref):
                    ax.plot(before * 1e3, "r.", ms=3, label="before")
                    ax.plot(after * 1e3, "b.", ms=3, label="after")
                    ax.set_xlabel("rest")
                    ax.set_ylabel(f"|{ref}| error, per mille")
                    ax.legend()
                figure(f"{sensor}_norm_errors", f"{sensor}: |{ref}| error before/after (paper Fig. 4b)", draw)
            if kind == "average":
                T, meas, pred = _col(t, "temperature"), _col(t, "measured"), _col(t, "predicted")
                rms = np.sqrt(np.mean((meas - pred) ** 2, axis=0))
                lines += [f"## {sensor}: thermal fit", "", f"residual RMS per axis {np.round(rms, 8).tolist()}", ""]

                def draw(ax, T=T, meas=meas, pred=pred):
                    for i, c in enumerate("xyz"):
                        ax.plot(T, meas[:, i] - meas[:, i].mean(), ".", ms=2, label=f"{c} measured")
                        ax.plot(T, pred[:, i] - meas[:, i].mean(), "-", lw=1, label=f"{c} fit")
                    ax.set_xlabel("temperature, degC")
                    ax.set_ylabel("bias minus mean")
                    ax.legend(fontsize=7, ncol=3)
                figure(f"{sensor}_thermal", f"{sensor}: bias vs temperature over the warm-up", draw)
        for t in results.values():
            sid = schemas.schema_of(t)
            if sid == "validation":
                summary = json.loads((t.schema.metadata or {}).get(b"imupipe.summary", b"{}"))
                lines += ["## Turn validation (eqs. 38-39)", "", "| quantity | value |", "|---|---|"]
                lines += [f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |"
                          for k, v in summary.items()]
                lines.append("")
                e0, e1 = _col(t, "angle_error_before_deg"), _col(t, "angle_error_after_deg")
                tol = float(summary.get("tolerance_deg", 0.1))

                def draw(ax, e0=e0, e1=e1, tol=tol):
                    ax.plot(e0, "r.", ms=3, label="before")
                    ax.plot(e1, "b.", ms=3, label="after")
                    ax.axhline(tol, color="k", lw=0.8, ls="--")
                    ax.axhline(-tol, color="k", lw=0.8, ls="--")
                    ax.set_xlabel("turn")
                    ax.set_ylabel("turn-angle error, deg")
                    ax.legend()
                figure("turn_errors", "turn-angle error before/after (paper Fig. 5)", draw)
            elif sid == "rests" and "accel_mean" in t.column_names:
                u = _col(t, "accel_mean")
                u = u / np.linalg.norm(u, axis=1, keepdims=True)

                def draw(ax, u=u):
                    lon, lat = np.degrees(np.arctan2(u[:, 2], u[:, 0])), np.degrees(np.arcsin(u[:, 1]))
                    ax.plot(lon, lat, "k.", ms=4)
                    ax.set_xlabel("azimuth of gravity in sensor x-z, deg")
                    ax.set_ylabel("elevation toward sensor y, deg")
                    ax.set_xlim(-180, 180)
                    ax.set_ylim(-90, 90)
                lines += [f"## Positions: {t.num_rows} rests", ""]
                figure("positions", "rest positions on the sphere (raw gravity direction)", draw)
        report = out_dir / "report.md"
        write_text(report, "\n".join(lines) + "\n")
        return [report, *written]


REPORT = ReportExporter()

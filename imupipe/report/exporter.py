"""The ``report`` exporter: ``report.md`` with PNG figures of a run's residual and validation tables.

Tables are recognised by their schema, not by the pipeline's names for them:
``residuals`` (per stage: |g| and |B| errors before/after, the thermal fit, the
gyro's turn residuals), ``turn_residuals`` (with the same stage's rest rows: the
whitened residuals of a joint fit and its chi2/dof per block), ``validation``
(turn-angle errors, eq. 39), ``rests`` (positions on the sphere) and ``stillness``
(what the segmentation saw, the signals with the rests shaded), ``noise`` with ``allan``
(the noise stage's terms and Allan plot). Needs the
``report`` extra (matplotlib). With ``context["figure_store"]`` (``imupipe run`` gives its
cache's ``figures/``), a figure drawn before from the same values (``figure_key``) is copied
from there instead of drawn.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from .. import schemas
from ..columns import kept_rows, vectors
from ..errors import require
from ..io import atomic_path, copy_file, table_digest, write_text
from ..paths import safe_name, under
from . import html, noise_figures, residual_figures, segment_figures


def _col(table: pa.Table, name: str) -> np.ndarray:
    if pa.types.is_fixed_size_list(table.schema.field(name).type):
        return vectors(table, name)
    return table.column(name).combine_chunks().to_numpy(zero_copy_only=False)


DPI = 110
PAD_IN = 2.0  # canvas beyond the axes on every side: the widest labels (the heat map's cell names, ~1.4 in) fit


def _new_figure(size: tuple[float, float], suptitle: str | None = None):
    """A figure whose axes (and ``suptitle``) sit as on a ``size`` (inches) figure, on a canvas
    ``PAD_IN`` larger on every side: labels and legends outside the axes stay on it, for
    ``_save`` to crop. Agg's, without pyplot (whose import is a third of matplotlib's)."""
    from matplotlib import rcParams as rc
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = size
    W, H = w + 2 * PAD_IN, h + 2 * PAD_IN
    fig = Figure(figsize=(W, H), dpi=DPI)
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=(rc["figure.subplot.left"] * w + PAD_IN) / W,
                        right=(rc["figure.subplot.right"] * w + PAD_IN) / W,
                        bottom=(rc["figure.subplot.bottom"] * h + PAD_IN) / H,
                        top=(rc["figure.subplot.top"] * h + PAD_IN) / H)
    if suptitle is not None:
        fig.suptitle(suptitle, y=(0.98 * h + PAD_IN) / H)  # matplotlib's 0.98 of the unpadded height
    return fig


def _save(fig, path: Path) -> None:
    """PNG of what is drawn plus 0.1 in, as ``bbox_inches="tight"`` gives, from one rendering
    cropped (savefig's tight box lays the figure out twice: ~20 ms a figure); when something
    reaches past the canvas, savefig draws that box (measured here: a second rendering, not two)."""
    from matplotlib.image import imsave

    canvas = fig.canvas
    canvas.draw()
    box = fig.get_tightbbox(canvas.get_renderer()).padded(0.1)
    w, h = fig.get_size_inches()
    with atomic_path(path) as tmp:
        if box.x0 < 0 or box.y0 < 0 or box.x1 > w or box.y1 > h:
            fig.savefig(tmp, format="png", dpi=DPI, bbox_inches=box)
            return
        top, bottom, left, right = (round(v * fig.dpi) for v in (h - box.y1, h - box.y0, box.x0, box.x1))
        imsave(tmp, np.asarray(canvas.buffer_rgba())[top:bottom, left:right], format="png", dpi=fig.dpi)


def _drawn(title: str, draw, panels: bool):
    """A figure drawn by ``draw``: given the figure (``panels``: it makes its own axes), else one
    axes, titled and gridded."""
    if panels:
        fig = _new_figure((8, 7), suptitle=title)
        draw(fig)
        return fig
    fig = _new_figure((7, 3.6))
    ax = fig.subplots()
    draw(ax)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    return fig


def _free_figure() -> None:
    """Free the figures saved so far now: a matplotlib figure is a web of reference cycles that
    holds its Agg raster (4-6 MiB), left to wait for the collector while the next figures are
    drawn (+28 MiB resident at the end of a report of 10 figures, the peak of a 1 h ``calibrate``
    run). What survives is frozen, so that each collection scans only the objects made since the
    last (a figure's): a few ms, where a full collection of the process costs ~20 ms."""
    gc.collect()
    gc.freeze()


@functools.cache
def _report_code() -> bytes:
    """The report package's sources: a figure drawn by other code is another figure."""
    h = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        h.update(path.name.encode() + path.read_bytes())
    return h.digest()


def _feed(h, x) -> None:
    """``x``'s content into hash ``h``; TypeError for a kind not handled here."""
    if x is None or isinstance(x, (bool, int, float, str)):
        h.update(repr(x).encode())  # repr: 1, 1.0 and "1" differ
    elif isinstance(x, np.ndarray) and not x.dtype.hasobject:
        h.update(f"a{x.dtype.str}{x.shape}".encode())
        h.update(np.ascontiguousarray(x).data)
    elif isinstance(x, pa.Table):
        h.update(b"t" + table_digest(x).encode())
    elif isinstance(x, dict):
        h.update(b"{")
        for k in sorted(x, key=repr):
            _feed(h, k)
            _feed(h, x[k])
        h.update(b"}")
    elif isinstance(x, (list, tuple)):
        h.update(b"[")
        for v in x:
            _feed(h, v)
        h.update(b"]")
    else:
        raise TypeError(f"no digest for {type(x).__name__}")


def figure_key(name: str, title: str, panels: bool, draw) -> str | None:
    """What a figure is drawn from: the report's code, matplotlib's version, its name and title,
    and the values its ``draw`` holds (defaults and closure); None when one of them is of a kind
    ``_feed`` does not digest (the figure is then always drawn)."""
    import matplotlib

    h = hashlib.sha256(_report_code())
    h.update(repr((matplotlib.__version__, name, title, panels)).encode())
    try:
        for value in (*(draw.__defaults__ or ()), *(c.cell_contents for c in draw.__closure__ or ())):
            _feed(h, value)
    except TypeError:
        return None
    return h.hexdigest()


def _copied(kept: Path, path: Path) -> bool:
    """``path`` becomes a copy of the figure store's ``kept``, drawn before from the same values;
    False when the store does not hold it (or it could not be read: the figure is drawn again)."""
    try:
        copy_file(kept, path)
    except OSError:
        return False
    return True


def _summary(table: pa.Table) -> dict:
    return json.loads((table.schema.metadata or {}).get(b"imupipe.summary", b"{}"))


def verdict_section(verdict: Mapping[str, Any] | None) -> list[str]:
    """Markdown: the verdict (``imupipe.verdict``) and its reasons, then every check made and
    what was not checked."""
    if not verdict:
        return []
    lines = [f"## Verdict: {verdict.get('status', '?')}", ""]
    lines += [f"- {r}" for r in verdict.get("reasons", [])] or ["Every check passed."]
    checks = verdict.get("checks", [])
    if checks:
        lines += ["", "| check | status | detail |", "|---|---|---|"]
        lines += [f"| {c['check']} | {c['status']} | {c['detail']} |" for c in checks]
    for what in verdict.get("not_checked", []):
        lines += ["", f"Not checked: {what}."]
    return [*lines, ""]


def _fit_lines(stage: str, turns: pa.Table) -> list[str]:
    """Markdown: the fit's chi2/dof per block and the turn table's chi2 per row."""
    summary = _summary(turns)
    lines = [f"## Whitened residuals of the joint fit ({stage})", ""]
    if summary.get("chi2_per_dof") is not None:
        band = 3 * np.sqrt(2 / max(summary["dof"], 1))
        head = (f"chi2/dof {summary['chi2_per_dof']:.3g} ({summary['chi2']:.4g} over {summary['dof']} dof): "
                f"1 +- {band:.2g} (3 sd) when the model (white noise, no omitted physics) holds.")
        lines += [head, "", "| block | rows | chi2 | effective dof | chi2/dof |", "|---|---|---|---|---|"]
        for name, b in summary.get("blocks", {}).items():
            if b["rows"] and b["chi2_per_dof"] is not None:
                lines.append(f"| {name} | {b['rows']} | {b['chi2']:.4g} | {b['dof']:.1f} | {b['chi2_per_dof']:.3g} |")
    used = _col(turns, "used").astype(bool)
    chi2, mismatch, t0 = _col(turns, "chi2"), _col(turns, "mismatch_deg"), _col(turns, "t_start_s")
    rows = 2 * int(used.sum())
    if rows:
        total = float(chi2[used].sum())
        lines.append(f"| turns, gravity measured at the rests | {rows} | {total:.4g} | ~{rows} | {total / rows:.3g} |")
    worst = ", ".join(f"turn {i} at {t0[i]:.0f} s ({mismatch[i]:.3g} deg, chi2 {chi2[i]:.3g})"
                      for i in np.argsort(chi2)[::-1][:3])
    return [*lines, "", f"Largest turn mismatches: {worst}.", ""]


def _draw_whitened(fig, rests: Mapping[str, pa.Table], turns: pa.Table) -> None:
    """Three panels against session time: accel rests, gyro rests (per axis), turns."""
    axes = fig.subplots(3, 1, sharex=True)
    for ax, sensor in zip(axes[:2], ("accel", "gyro"), strict=True):
        t = rests.get(sensor)
        if t is not None and t.num_rows:
            z, ts = _col(t, "normalised"), _col(t, "t_s") / 60
            for i, (c, m) in enumerate(zip("xyz", "o^s", strict=True)):
                ax.plot(ts, z[:, i], m, ms=3, alpha=0.8, label=c)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        ax.set_ylabel(f"{sensor} rest\n(mean - model)/sigma", fontsize=8)
    w, ts = _col(turns, "whitened"), _col(turns, "t_start_s") / 60
    used = _col(turns, "used").astype(bool)
    for i, m in enumerate("ox"):
        axes[2].plot(ts[used], w[used, i], m, ms=3, label=f"component {i + 1}")
    if (~used).any():
        axes[2].plot(ts[~used], np.zeros((~used).sum()), "k|", ms=8, label="left out")
    axes[2].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    axes[2].set_ylabel("turn gravity mismatch\nwhitened", fontsize=8)
    axes[2].set_xlabel("session time, min")
    for ax in axes:
        ax.axhline(3, color="k", lw=0.8, ls="--")
        ax.axhline(-3, color="k", lw=0.8, ls="--")
        ax.grid(alpha=0.3)


def _by_stage(tables: Mapping[str, pa.Table]) -> dict[tuple[str, str, str], pa.Table]:
    """Residual rows grouped by (stage, sensor, kind)."""
    out: dict[tuple[str, str, str], pa.Table] = {}
    for t in tables.values():
        if schemas.schema_of(t) != "residuals":
            continue
        stage, sensor, kind = (_col(t, c) for c in ("stage", "sensor", "kind"))
        for key in sorted(set(zip(stage, sensor, kind, strict=True))):
            mask = (stage == key[0]) & (sensor == key[1]) & (kind == key[2])
            out[key] = kept_rows(t, mask)
    return out


class ReportExporter:
    """Writes ``out_dir/report.md``, ``out_dir/figures/*.png`` and ``report.html`` (the same page,
    figures embedded)."""

    name = "report"
    version = "4"  # bump when the report or a figure changes for the same tables (export cache)
    writes = ("report.md", "report.html", "figures")

    def export(self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path) -> list[Path]:
        require("matplotlib", "report")
        try:
            return self._write(results, context, Path(out_dir))
        finally:
            gc.unfreeze()  # what _free_figure froze: the process's objects as they were

    def _write(self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path) -> list[Path]:
        figs = out_dir / "figures"
        written: list[Path] = []
        lines = [f"# Calibration report: {context.get('session', '?')}", "",
                 f"pipeline `{context.get('pipeline', '?')}`, imupipe {context.get('imupipe_version', '?')}", ""]
        lines += verdict_section(context.get("verdict"))
        if context.get("skipped"):
            lines += ["Skipped stages: " + ", ".join(f"`{k}` ({v})" for k, v in dict(context["skipped"]).items()), ""]
        groups = _by_stage(results)
        store = context.get("figure_store")

        def figure(name: str, title: str, draw, stage: str = "", panels: bool = False) -> None:
            if f"{name}.png" in {p.name for p in written}:  # the same plot of another stage
                name = f"{stage}_{name}"
            path = under(figs, f"{safe_name(name, 'figure')}.png")
            key = figure_key(name, title, panels, draw) if store else None
            kept = None if key is None else Path(store) / key[:2] / f"{key}.png"
            if not (kept is not None and _copied(kept, path)):
                _save(_drawn(title, draw, panels), path)
                _free_figure()
                if kept is not None:
                    with contextlib.suppress(OSError):  # a store it cannot write only costs a redraw
                        copy_file(path, kept)
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
                figure(f"{sensor}_norm_errors", f"{sensor}: |{ref}| error before/after (paper Fig. 4b)", draw,
                       stage)
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
            if sid == "turn_residuals" and t.num_rows:
                stage = str(_col(t, "stage")[0])
                lines += _fit_lines(stage, t)
                rests = {s: groups[(stage, s, "rest")] for s in ("accel", "gyro") if (stage, s, "rest") in groups}
                figure(f"{stage}_whitened", f"{stage}: whitened residuals per rest and per turn",
                       lambda fig, rests=rests, t=t: _draw_whitened(fig, rests, t), stage, panels=True)
            elif sid == "validation":
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
            elif sid == "residual_map":
                doc = json.loads(t.schema.metadata[b"imupipe.residual_map"])
                lines += residual_figures.map_lines(doc)
                for sensor in ("accel", "gyro"):
                    figure(f"residual_map_{sensor}", f"{sensor}: chi2/dof per cell (* flagged)",
                           lambda fig, doc=doc, sensor=sensor: residual_figures.draw_heat_map(fig, doc, sensor),
                           panels=True)
                samples = next((x for x in results.values() if schemas.schema_of(x) == "sample_residuals"), None)
                if samples is not None:
                    figure("residuals_in_time", "whitened residuals along the session",
                           lambda fig, s=samples, doc=doc: residual_figures.draw_time_series(fig, s, doc),
                           panels=True)
            elif sid == "diagnosis":
                doc = json.loads(t.schema.metadata[b"imupipe.diagnosis"])
                lines += residual_figures.diagnosis_lines(doc)
                proved = [f for f in doc["findings"] if f["heldout_rms_before"] is not None]
                if proved:
                    figure("diagnosis_heldout", "held-out residual RMS without and with each term",
                           lambda ax, f=proved: residual_figures.draw_heldout(ax, f))
            elif sid == "noise" and t.num_rows:
                lines += noise_figures.lines(t)
                curves = next((x for x in results.values() if schemas.schema_of(x) == "allan"), None)
                if curves is not None and curves.num_rows:
                    figure("allan_deviation", "Allan deviation of the longest rests",
                           lambda fig, c=curves: noise_figures.draw(fig, c), panels=True)
            elif sid == "stillness" and t.num_rows:
                lines += segment_figures.lines(t)
                figure("rests_in_time", "raw signals with the rests found shaded",
                       lambda fig, t=t: segment_figures.draw(fig, t), panels=True)
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
        text = "\n".join(lines) + "\n"
        write_text(report, text)
        page = out_dir / "report.html"  # the same, figures embedded: one file for a browser
        write_text(page, html.render(text, out_dir))
        return [report, page, *written]


REPORT = ReportExporter()

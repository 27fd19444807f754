"""``imupipe diagnose SESSION...`` with several sessions of one unit: each diagnosed, then pooled.

Every session is calibrated and diagnosed as ``run_sessions(..., diagnose=True)`` does (its
own ``<out>/<session>/diagnosis.json``); then, from the cached stage outputs, each session's
per-sample model is evaluated again and the models are pooled (``diagnosis/pool.py``) into
``<out>/pooled/diagnosis.json`` and ``report.md`` (``pooled-<hash>`` when a session is itself
named ``pooled``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import ImupipeError
from ..ingest import read_recording
from ..io import write_text
from ..paths import under
from ..plugins import Registry, make_registry
from ..progress import progress
from .api import CACHE_DIR, MANIFEST, _resolved, run_sessions, session_ids
from .cache import Cache
from .config import load_pipeline
from .dag import Node, Pipeline
from .runner import run_session

POOLED = "pooled"
TRIADS = ("accel", "gyro", "mag")


def pooled_folder(ids: Sequence[str]) -> str:
    """``pooled``, or ``pooled-<hash of the sessions>`` when a session's own folder has that name."""
    if POOLED not in {i.lower() for i in ids}:
        return POOLED
    return f"{POOLED}-{hashlib.sha256(chr(0).join(ids).encode()).hexdigest()[:8]}"


def diagnose_sessions(sessions: Sequence[Path], pipeline: Path | None = None, out: Path = Path("imupipe-out"),
                      quiet: bool = False, *, registry: Registry | None = None,
                      overrides: Sequence[str] = ()) -> tuple[list[Path], Path]:
    """Diagnose each session, then all of them pooled; returns (the calibration files written,
    the pooled ``diagnosis.json``). Raises ``ImupipeError`` naming the file when the sessions are
    evidently not of one unit (other sensors, a calibration or gravity far from the first's)."""
    from ..diagnosis.diagnose import noise_misfit
    from ..diagnosis.pool import diagnose_pooled
    from ..stages.residuals import evaluation

    registry = registry or make_registry()
    sessions = list({_resolved(s): Path(s) for s in sessions}.values())
    if len(sessions) < 2:
        raise ImupipeError("a pooled diagnosis needs at least two different sessions")
    spec = load_pipeline(pipeline, registry, tuple(overrides), diagnose=True)
    node = _diagnose_node(spec)
    _check_sensors(sessions, spec, registry)  # before any calibration: a mix-up fails at once
    written = run_sessions(sessions, pipeline, out, quiet, registry=registry, overrides=overrides, diagnose=True)
    ids = session_ids(sessions)
    cache = Cache(under(Path(out), CACHE_DIR))
    inputs = []
    with progress(quiet) as p:
        task = p.add_task("pooling", total=len(sessions) + 1)
        for session, sid in zip(sessions, ids, strict=True):
            run = run_session(session, spec, registry, cache, under(Path(out), sid) / MANIFEST)  # cached
            inputs.append({})
            for port, ref in node.inputs.items():
                if ref.is_session:
                    if ref.port in run.source.names():
                        inputs[-1][port] = run.source.table(ref.port)
                elif (table := run.table(ref)) is not None:
                    inputs[-1][port] = table
        walks = _walks(inputs, node.params)
        evaluations = []
        for session, one, walk in zip(sessions, inputs, walks, strict=True):
            try:
                evaluations.append(evaluation(one, node.params, walk))
            except ImupipeError as exc:
                raise ImupipeError(f"{session}: {exc}") from exc
            p.advance(task)
        effects = {name: registry.get("effects", name) for name in registry.names("effects")}
        misfit = frozenset().union(*(noise_misfit(_own(Path(out), sid, "residual_map.json"), node.params.fdr_q)
                                     for sid in ids))
        doc = diagnose_pooled(evaluations, effects, ids, q=node.params.fdr_q, files=[str(s) for s in sessions],
                              latitude_deg=node.params.latitude_deg, misfit=misfit)
        doc["session_files"] = [str(s) for s in sessions]
        doc["bias_walks"] = {sid: {"q_accel": list(a), "q_gyro": list(g)} for sid, (a, g) in zip(ids, walks)}
        doc["single_session"] = _single_session(Path(out), ids, doc)
        p.advance(task)
    folder = under(Path(out), pooled_folder(ids))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "diagnosis.json"
    write_text(path, json.dumps(doc, indent=1, default=float))
    write_text(folder / "report.md", "\n".join(report_lines(doc)))
    return written, path


def _check_sensors(sessions: list[Path], spec: Pipeline, registry: Registry) -> None:
    """Raise ``ImupipeError`` naming the file whose triads differ from the first session's."""
    first = None
    for session in sessions:
        streams = read_recording(session, registry, spec.reader).device(spec.device)
        triads = sorted(s for s in TRIADS if s in streams)
        if first is not None and triads != first:
            raise ImupipeError(f"{session}: records {', '.join(triads)}, {sessions[0]} {', '.join(first)}: "
                               "not recordings of one unit; pool only sessions of the same sensors")
        first = first or triads


def _walks(inputs: list[dict], params) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each session's bias-walk intensities for the pooled model: its own (``null_walks``), or the
    pooled estimate (``diagnosis.pool.pooled_walks``: one k for all) where that is larger."""
    from ..diagnosis.pool import pooled_walks
    from ..models import Calibration
    from ..observations import Rests
    from ..stages.refine import STANDARD_GRAVITY
    from ..stages.residuals import null_walks

    cals = [Calibration.from_tables(one["calibration"]) for one in inputs]
    g = params.g_m_s2 or float(cals[0]["gyro"].details.get("joint", {}).get("gravity_m_s2", STANDARD_GRAVITY))
    rests = [Rests.from_table(one["rests"]) for one in inputs]
    q_a, q_g = pooled_walks(rests, [c["accel"] for c in cals], [c["gyro"] for c in cals], g)
    return [(np.maximum(a, q_a), np.maximum(b, q_g)) for a, b in (null_walks(c, r, g) for c, r in zip(cals, rests))]


def _diagnose_node(spec: Pipeline) -> Node:
    for node in spec.nodes.values():
        if node.stage.name == "diagnose":
            return node
    raise ImupipeError(f"{spec.path}: no diagnose stage")  # load_pipeline(diagnose=True) made one


def _single_session(out: Path, ids: list[str], doc: dict) -> dict:
    """What each session's own diagnosis said of the effects the pooled one tested: its findings'
    names and, per effect and sensor, the largest visible fraction."""
    single = {}
    for sid in ids:
        own = _own(out, sid, "diagnosis.json") or {"findings": [], "tested": []}
        single[sid] = {"findings": [f["effect"] for f in own["findings"]], "visible_fraction": _visible(own)}
    return single


def _own(out: Path, sid: str, name: str) -> dict | None:
    """A session's own document (``diagnosis.json``, ``residual_map.json``), if it was written."""
    path = out / sid / name
    return json.loads(path.read_text()) if path.exists() else None


def _visible(doc: dict) -> dict[str, float]:
    """``effect/sensor`` -> the largest visible fraction of its tested terms."""
    out: dict[str, float] = {}
    for t in doc["tested"]:
        key = f"{t['effect']}/{t['sensor']}"
        out[key] = max(out.get(key, 0.0), t["visible_fraction"])
    return out


def report_lines(doc: dict) -> list[str]:
    """``report.md`` of a pooled diagnosis: the sessions, the diagnosis in words, and the effects the
    sessions show only together."""
    from ..report.residual_figures import diagnosis_lines

    lines = [f"# Pooled diagnosis of {len(doc['sessions'])} sessions of one unit", ""]
    lines += [f"- {sid}: {path}" for sid, path in zip(doc["sessions"], doc["session_files"], strict=True)]
    lines += ["", f"Shared by the sessions: {', '.join(doc['shared'])}; per session: "
                  f"{', '.join(doc['per_session'])} and every nuisance (gravity directions, bias walks, "
                  "attitude paths).", ""]
    lines += diagnosis_lines(doc)
    lines += ["## Visible fraction: each session alone and pooled", "",
              "| effect/sensor | " + " | ".join(doc["sessions"]) + " | pooled |",
              "|---" * (len(doc["sessions"]) + 2) + "|"]
    for key, v in _visible(doc).items():
        own = [doc["single_session"][s]["visible_fraction"].get(key) for s in doc["sessions"]]
        lines.append(f"| {key} | " + " | ".join("-" if x is None else f"{x:.3f}" for x in own) + f" | {v:.3f} |")
    return lines + [""]

"""``imupipe status``: which stages would rerun and why, decided before anything runs.

Compares the key parts each stage would have now (stage version and plugin
distribution, validated params, solver, input digests) with those recorded in
the session's run manifest. Session inputs are digested from the files and the
reader that would read them; an upstream input's digest is known only when the
upstream stage is fresh (else it may or may not change: early cutoff decides
when it runs).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .cache import Cache, KeyParts, key_parts, stream_digest
from .dag import Pipeline


@dataclass(frozen=True)
class StageState:
    stage: str
    state: str  # fresh | stale | skipped
    reasons: tuple[str, ...] = ()


def stage_states(
    pipeline: Pipeline,
    session: Path,
    manifest: dict | None,
    cache: Cache,
    reader: dict | str | None = None,
    digest: str | None = None,
) -> list[StageState]:
    """The state of every stage of ``pipeline`` on ``session`` given its last run manifest.

    ``reader``: ``reader_identity`` of the reader that would read the session now,
    or why none would (a string); ``digest``: the session's digest now (None: no file).
    """
    manifest = manifest or {}
    records = manifest.get("stages", {})
    if isinstance(reader, str):
        return [StageState(k, "stale", (reader,)) for k in pipeline.nodes]
    same_session = (
        digest is not None
        and digest == manifest.get("session_digest")
        and manifest.get("device") == pipeline.device
        and manifest.get("reader") == reader
    )
    session_change = _session_change(digest, reader, manifest)
    streams = manifest.get("streams") if same_session else None
    fresh_outputs: dict[str, dict] = {}
    skipped: set[str] = set()
    states = []
    for key, node in pipeline.nodes.items():
        rec = records.get(key)
        if digest is None:
            states.append(StageState(key, "stale", (f"session file {session} is missing",)))
            continue
        # a stage skipped last time on the same bytes (a stream it needs is absent) stays skipped
        why_skip = _skip_reason(node, streams, skipped)
        if why_skip:
            skipped.add(key)
            states.append(StageState(key, "skipped", (why_skip,)))
            continue
        if rec is None or rec.get("status") not in ("ran", "cached") or not rec.get("parts"):
            why = (
                "never run"
                if rec is None
                else f"not run last time ({rec.get('reason') or rec.get('status')})"
            )
            states.append(StageState(key, "stale", (why,)))
            continue
        old = KeyParts.from_dict(rec["parts"])
        inputs, unknown, stale_up = {}, set(), []
        for port, ref in node.inputs.items():
            if ref.is_session:
                if streams is None or ref.port in streams:  # else an absent optional stream
                    inputs[port] = stream_digest(digest, pipeline.device, ref.port, reader)
            elif ref.source in fresh_outputs:
                inputs[port] = fresh_outputs[ref.source].get(ref.port, "")
            elif ref.source not in skipped:
                unknown.add(port)
                if ref.source not in stale_up:
                    stale_up.append(ref.source)
        new = key_parts(node, inputs)
        reasons = _differences(old, new, node.inputs, set(inputs) | unknown, session_change)
        if stale_up:
            names = ", ".join(repr(s) for s in stale_up)
            reasons.append(
                f"upstream {names} {'is' if len(stale_up) == 1 else 'are'} stale "
                "(reruns unless the upstream output comes out unchanged)"
            )
        if not reasons and cache.digests(new.key) is None:
            reasons.append("its cached outputs are gone")
        if reasons:
            states.append(StageState(key, "stale", tuple(reasons)))
        else:
            fresh_outputs[key] = rec.get("outputs", {})
            states.append(StageState(key, "fresh"))
    return states


def _skip_reason(node, streams: list[str] | None, skipped: set[str]) -> str:
    for port, ref in node.inputs.items():
        if port in node.stage.optional_inputs:
            continue
        if ref.is_session and streams is not None and ref.port not in streams:
            return f"the session has no {ref.port!r} stream"
        if not ref.is_session and ref.source in skipped:
            return f"upstream {ref.source!r} is skipped"
    return ""


def _session_change(digest: str | None, reader: dict | None, manifest: dict) -> str:
    """Why the session inputs' digests changed: the bytes, or else the reader."""
    if digest != manifest.get("session_digest"):
        return "the session file changed"
    old = manifest.get("reader")
    if old != reader and isinstance(old, dict) and isinstance(reader, dict):
        return "; ".join(_reader_changes(old, reader)) or "the reader changed"
    if old != reader:
        return "the reader changed"
    return "the device changed"


def _reader_changes(old: dict, new: dict) -> list[str]:
    """``reader csv changed 0.1 -> 0.2``, also for the readers a manifest delegates to."""
    if old.get("name") != new.get("name"):
        return [f"reader changed {old.get('name')} -> {new.get('name')}"]
    out = []
    before, after = (
        {"name": d.get("distribution"), "version": d.get("version")} for d in (old, new)
    )
    if before != after:
        out.append(f"reader {new['name']} changed {_versions(before, after)}")
    before, after = (
        {d["name"]: f"{d.get('distribution')} {d.get('version')}" for d in r.get("delegates", [])}
        for r in (old, new)
    )
    return out + _dict_changes("manifest reader", before, after)


def _versions(old: dict | None, new: dict | None) -> str:
    """``1.0 -> 1.1`` within one distribution, else ``a 1.0 -> b 2.0`` (``built in``: none)."""
    if old and new and old.get("name") == new.get("name"):
        return f"{old.get('version')} -> {new.get('version')}"
    a, b = (f"{d['name']} {d.get('version')}" if d and d.get("name") else "no distribution"
            for d in (old, new))
    return f"{a} -> {b}"


def _dist_change(prefix: str, old: dict | None, new: dict | None) -> list[str]:
    """``plugin imupipe-x dist version changed 1.0 -> 1.1`` (``prefix``: whose plugin)."""
    if (old or None) == (new or None):
        return []
    if old and new and old.get("name") == new.get("name"):
        return [f"{prefix}plugin {new['name']} dist version changed {_versions(old, new)}"]
    return [f"{prefix}plugin dist changed {_versions(old, new)}"]


def _differences(
    old: KeyParts, new: KeyParts, wiring, wired: set[str], session_change: str
) -> list[str]:
    out = []
    if old.stage != new.stage:
        out.append(f"stage changed {old.stage} -> {new.stage}")
    else:
        if old.version != new.version:
            out.append(f"version changed {old.version} -> {new.version}")
        out += _dist_change("", old.distribution, new.distribution)
    params_old, params_new = dict(old.params), dict(new.params)
    if old.solver or new.solver:  # the solver's name is reported below, once
        params_old.pop("solver", None)
        params_new.pop("solver", None)
    out += _dict_changes("param", params_old, params_new)
    if (old.solver or {}).get("name") != (new.solver or {}).get("name"):
        out.append(
            f"solver changed {(old.solver or {}).get('name')} -> {(new.solver or {}).get('name')}"
        )
    elif old.solver and new.solver:
        if old.solver["version"] != new.solver["version"]:
            out.append(
                f"solver {new.solver['name']} version changed {old.solver['version']} -> "
                f"{new.solver['version']}"
            )
        out += _dist_change(
            f"solver {new.solver['name']} ",
            old.solver.get("distribution"),
            new.solver.get("distribution"),
        )
        out += _dict_changes("solver param", old.solver["params"], new.solver["params"])
    for port in sorted(set(old.inputs) | wired):
        if port not in old.inputs:
            out.append(f"input {port!r} newly wired")
        elif port not in wired:
            out.append(f"input {port!r} no longer wired")
        elif port in new.inputs and new.inputs[port] != old.inputs[port]:
            ref = wiring[port]
            what = session_change if ref.is_session else f"{ref} changed"
            out.append(f"input {port!r} changed ({what})")
    return out


def _dict_changes(label: str, old: dict, new: dict) -> list[str]:
    out = []
    for name in sorted(set(old) | set(new)):
        if name not in old:
            out.append(f"{label} {name} added ({new[name]!r})")
        elif name not in new:
            out.append(f"{label} {name} removed")
        elif old[name] != new[name]:
            out.append(f"{label} {name} changed {old[name]!r} -> {new[name]!r}")
    return out


def render(
    session: Path, pipeline: Pipeline, states: list[StageState], run_dir: Path, note: str = "",
    last_error: str | None = None,
) -> str:
    """Text for one session: a header, then one line per stage.

    ``note`` says where the pipeline came from when it was not given; ``last_error``
    why the last run failed (from run.json).
    """
    stale = sum(s.state == "stale" for s in states)
    head = (
        f"{session}  (pipeline {pipeline.name!r}{note}, results in {run_dir}): "
        f"{stale} stale, {sum(s.state == 'fresh' for s in states)} fresh"
    )
    width = max((len(s.stage) for s in states), default=0)
    lines = [head] + ([f"  last run failed: {last_error}"] if last_error else [])
    for s in states:
        lines.append(f"  {s.state:<7} {s.stage:<{width}}  {'; '.join(s.reasons)}".rstrip())
    return "\n".join(lines)

"""The wiring of a pipeline: references between stages, checked and put in run order.

A pipeline is a DAG whose nodes are configured stages and whose edges are
references ``"<stage>.<output>"``; ``"session.<stream>"`` is a raw stream of the
recording. Everything here is checked before any data is read: unknown
references, cycles, unwired inputs and schema mismatches on an edge.
"""

from __future__ import annotations

import graphlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..components import BoundSolver, Params, Stage
from ..errors import ConfigError

SESSION = "session"
SESSION_STREAMS = ("accel", "gyro", "mag", "temperature", "sections")


@dataclass(frozen=True)
class Ref:
    """A table a stage reads: ``source`` a stage key or ``"session"``; ``port`` an output/stream."""

    source: str
    port: str

    @property
    def is_session(self) -> bool:
        return self.source == SESSION

    def __str__(self) -> str:
        return f"{self.source}.{self.port}"


@dataclass(frozen=True)
class Node:
    """One configured stage: ``key`` is its free name in the pipeline file."""

    key: str
    stage: Stage
    params: Params
    solver: BoundSolver | None
    inputs: Mapping[str, Ref]  # port -> reference
    # {"name", "version"} of the plugin distribution providing the stage / solver (cache keys);
    # None for imupipe's own components
    distribution: Mapping | None = None
    solver_distribution: Mapping | None = None


@dataclass(frozen=True)
class Pipeline:
    """A validated pipeline: nodes in run (topological) order."""

    name: str
    path: Path
    nodes: Mapping[str, Node]
    description: str = ""
    device: str | None = None
    reader: str | None = None
    export_calibration: tuple[Ref, ...] = ()
    export_reports: tuple[Ref, ...] = ()
    raw: Mapping = field(default_factory=dict)
    overrides: tuple[str, ...] = ()  # ``--set STAGE.PARAM=VALUE`` applied to the file

    def downstream(self, key: str) -> set[str]:
        """Every node that reads, directly or not, an output of ``key``."""
        out: set[str] = set()
        for node in self.nodes.values():  # topological order: one pass suffices
            if any(r.source == key or r.source in out for r in node.inputs.values()):
                out.add(node.key)
        return out


def parse_ref(text: str, where: str) -> Ref:
    """``"rests.rests"`` -> Ref("rests", "rests"); errors name ``where`` (a key path)."""
    source, sep, port = text.partition(".")
    if not sep or not source or not port or "." in port:
        raise ConfigError(
            f"{where}: {text!r} is not a reference; write 'session.<stream>' or '<stage>.<output>'"
        )
    return Ref(source, port)


def build(
    path: Path, name: str, nodes: list[Node], wiring_paths: Mapping[str, str], **fields
) -> Pipeline:
    """Check the wiring of ``nodes`` and return the pipeline in topological order.

    ``wiring_paths`` maps a node key to the key path of its ``inputs`` table in the
    file (for messages).
    """
    by_key = {n.key: n for n in nodes}
    graph: dict[str, set[str]] = {}
    for node in nodes:
        where = f"{path}: {wiring_paths[node.key]}"
        stage = node.stage
        for port, ref in node.inputs.items():
            at = f"{where}.{port}"
            if port not in stage.inputs:
                raise ConfigError(
                    f"{at}: stage {stage.name!r} has no input {port!r}; "
                    f"its inputs: {', '.join(stage.inputs) or 'none'}"
                )
            expected = stage.inputs[port]
            found = _schema_of_ref(ref, by_key, at)
            if found != expected:
                raise ConfigError(
                    f"{at}: {str(ref)!r} is a table of schema {found!r}, but input {port!r} "
                    f"of stage {stage.name!r} expects schema {expected!r}"
                )
        missing = [
            p for p in stage.inputs if p not in node.inputs and p not in stage.optional_inputs
        ]
        if missing:
            raise ConfigError(
                f"{where}: stage {stage.name!r} needs input(s) {', '.join(missing)}; "
                "wire each to 'session.<stream>' or '<stage>.<output>'"
            )
        graph[node.key] = {r.source for r in node.inputs.values() if not r.is_session}
    try:
        order = list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        cycle = exc.args[1]
        raise ConfigError(
            f"{path}: stages: the inputs form a cycle {' -> '.join(reversed(cycle))}; "
            "a stage cannot depend on its own output"
        ) from None
    return Pipeline(name=name, path=path, nodes={k: by_key[k] for k in order}, **fields)


def check_export(
    path: Path, refs: list[str], nodes: Mapping[str, Node], where: str, schema: str | None
) -> tuple[Ref, ...]:
    """Resolve ``[export]`` references; with ``schema``, each must be a table of that schema."""
    out = []
    for i, text in enumerate(refs):
        at = f"{path}: {where}[{i}]"
        ref = parse_ref(text, at)
        if ref.is_session:
            raise ConfigError(
                f"{at}: exports name stage outputs, not raw session streams ({text!r})"
            )
        found = _schema_of_ref(ref, nodes, at)
        if schema is not None and found != schema:
            raise ConfigError(f"{at}: {text!r} is a table of schema {found!r}, expected {schema!r}")
        out.append(ref)
    return tuple(out)


def _schema_of_ref(ref: Ref, nodes: Mapping[str, Node], at: str) -> str:
    if ref.is_session:
        if ref.port not in SESSION_STREAMS:
            raise ConfigError(
                f"{at}: no session stream {ref.port!r}; streams: {', '.join(SESSION_STREAMS)}"
            )
        return ref.port
    node = nodes.get(ref.source)
    if node is None:
        raise ConfigError(
            f"{at}: refers to stage {ref.source!r}, which is not in this pipeline; "
            f"stages: {', '.join(sorted(nodes)) or 'none'}"
        )
    if ref.port not in node.stage.outputs:
        raise ConfigError(
            f"{at}: stage {ref.source!r} ({node.stage.name}) has no output {ref.port!r}; "
            f"its outputs: {', '.join(node.stage.outputs)}"
        )
    return node.stage.outputs[ref.port]

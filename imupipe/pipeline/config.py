"""Pipeline files (``pipelines/*.toml``): read with tomllib, validated with pydantic.

Every error names the file and the key path, e.g.
``pipelines/x.toml: stages.gyro.params.max_turn_deg: unknown key``. Stage params
are validated by the stage's own ``Params`` model, ``solver_params`` by the
solver's. Nothing here reads data.
"""

from __future__ import annotations

import difflib
import re
import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..components import BoundSolver, Params
from ..errors import ConfigError, ImupipeError, PluginError, describe_validation
from ..plugins import Registry
from ..resources import shipped_dir
from . import dag
from .cache import distribution

_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]*$")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class InputSection(_Section):
    device: str | None = None  # which device of the recording; None: the only one
    reader: str | None = None  # force a reader instead of letting the file choose


class StageSection(_Section):
    uses: str
    inputs: dict[str, str] = Field(default_factory=dict)
    params: dict[str, Any] = Field(default_factory=dict)


class ExportSection(_Section):
    calibration: list[str] = Field(default_factory=list)
    reports: list[str] = Field(default_factory=list)


class PipelineFile(_Section):
    name: str
    description: str = ""
    input: InputSection = Field(default_factory=InputSection)
    stages: dict[str, StageSection]
    export: ExportSection = Field(default_factory=ExportSection)


def default_pipeline_path() -> Path:
    """The shipped ``pipelines/default.toml``."""
    return shipped_dir("pipelines") / "default.toml"


def shipped_pipelines() -> dict[str, Path]:
    """Name -> file of every shipped pipeline (``pipelines/*.toml``), sorted by name."""
    try:
        folder = shipped_dir("pipelines")
    except ImupipeError:
        return {}
    return {p.stem: p for p in sorted(folder.glob("*.toml"))}


def resolve_path(path: Path | str | None) -> Path:
    """The pipeline file to use: ``path`` (a file, or the name of a shipped pipeline), or the
    default one (an error if it is missing)."""
    if path is None:
        default = default_pipeline_path()
        if not default.is_file():
            raise ConfigError(
                f"{default}: the default pipeline is missing; give one with --pipeline FILE"
            )
        return default
    path = Path(path)
    if path.is_file():
        return path
    shipped = shipped_pipelines()
    if path.parent == Path(".") and path.name in shipped:  # a bare name: a shipped pipeline
        return shipped[path.name]
    raise ConfigError(
        f"{path}: no such pipeline file, nor a shipped pipeline of that name; shipped: "
        f"{', '.join(shipped) or 'none'} (imupipe pipelines lists them)"
    )


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"accel.g_m_s2=9.81"`` -> (["accel", "g_m_s2"], 9.81); the value is read as a TOML
    value (numbers, true/false, strings, arrays, inline tables), else taken as a bare string."""
    key, sep, value = text.partition("=")
    parts = key.strip().split(".")
    if not sep or len(parts) < 2 or not all(parts) or not value.strip():
        raise ConfigError(
            f"--set {text!r}: expected STAGE.PARAM=VALUE, e.g. --set accel.g_m_s2=9.81"
        )
    try:
        parsed = tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value.strip()  # a bare word: a string (solver=ellipsoid_svd)
    return parts, parsed


def apply_overrides(raw: dict, overrides: tuple[str, ...], path: Path, registry: Registry) -> dict:
    """The pipeline file's content with each ``STAGE.PARAM=VALUE`` set (``input.device=...``,
    ``input.reader=...`` too). An unknown stage or parameter is an error naming it; the values
    are then validated with the rest of the file."""
    import copy

    raw = copy.deepcopy(raw)
    stages = raw.get("stages") if isinstance(raw.get("stages"), dict) else {}
    for text in overrides:
        parts, value = parse_override(text)
        head, rest = parts[0], parts[1:]
        if head == "input":
            if len(rest) != 1 or rest[0] not in InputSection.model_fields:
                raise ConfigError(
                    f"--set {text}: [input] has no key {'.'.join(rest)!r}; keys: "
                    f"{', '.join(InputSection.model_fields)}"
                )
            raw.setdefault("input", {})[rest[0]] = value
            continue
        if head not in stages:
            raise ConfigError(
                f"--set {text}: no stage {head!r} in {path}; its stages: "
                f"{', '.join(stages) or 'none'}"
            )
        section = stages[head]
        uses = section.get("uses") if isinstance(section, dict) else None
        if uses in registry.names("stages"):
            fields = registry.get("stages", uses).params.model_fields
            if rest[0] not in fields:
                close = difflib.get_close_matches(rest[0], list(fields), n=1)
                hint = f"did you mean {close[0]!r}? " if close else ""
                raise ConfigError(
                    f"--set {text}: stage {head!r} ({uses}) has no parameter {rest[0]!r}; "
                    f"{hint}its parameters: {', '.join(fields) or 'none'}"
                )
        node = section.setdefault("params", {})
        for part in rest[:-1]:  # solver_params.fix_d33: a table inside params
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {text}: {part!r} is not a table of parameters")
        node[rest[-1]] = value
    return raw


def _with_diagnosis(raw: dict, path: Path) -> dict:
    """The pipeline with its ``map_residuals`` stage(s) run as ``diagnose`` (same inputs and
    params, one more output exported: diagnosis.json)."""
    stages = raw.get("stages", {}) if isinstance(raw, dict) else {}
    keys = [k for k, s in stages.items() if isinstance(s, dict) and s.get("uses") == "map_residuals"]
    if not keys:
        raise ConfigError(f"{path}: no map_residuals stage: imupipe diagnose needs the residual map "
                          "(use the default pipeline, or add a map_residuals stage as it does)")
    raw = {**raw, "stages": {**stages}, "export": dict(raw.get("export", {}))}
    reports = list(raw["export"].get("reports", []))
    for k in keys:
        raw["stages"][k] = {**stages[k], "uses": "diagnose"}
        reports.append(f"{k}.diagnosis")
    raw["export"]["reports"] = reports
    return raw


def load_pipeline(
    path: Path | str | None, registry: Registry, overrides: tuple[str, ...] | list[str] = (), *,
    diagnose: bool = False,
) -> dag.Pipeline:
    """Read, validate and wire a pipeline file (``None``: the default pipeline; a bare name: a
    shipped one), with ``overrides`` (``--set STAGE.PARAM=VALUE``) applied before validation;
    ``diagnose``: its residual map stage becomes the diagnosis (``imupipe diagnose``)."""
    path = resolve_path(path)
    overrides = tuple(overrides)
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid TOML: arrays or tables nested too deeply") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the pipeline ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file; expected a pipeline TOML") from None
    if diagnose:
        raw = _with_diagnosis(raw, path)
    if overrides:
        raw = apply_overrides(raw, overrides, path, registry)
        try:
            return _load(path, raw, registry, overrides)
        except ConfigError as exc:
            raise ConfigError(f"{exc} (with --set {' --set '.join(overrides)})") from None
    return _load(path, raw, registry, overrides)


def _load(path: Path, raw: dict, registry: Registry, overrides: tuple[str, ...]) -> dag.Pipeline:
    try:
        spec = PipelineFile.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(_message(path, exc, (), PipelineFile)) from None

    if spec.input.reader is not None:
        _lookup(registry, "readers", spec.input.reader, path, "input.reader")
    nodes, wiring = [], {}
    for key, section in spec.stages.items():
        where = f"stages.{key}"
        if not _KEY.match(key) or key == dag.SESSION:
            raise ConfigError(
                f"{path}: {where}: {key!r} cannot name a stage; use letters, digits, _ "
                f"or - (and not {dag.SESSION!r})"
            )
        stage = _lookup(registry, "stages", section.uses, path, f"{where}.uses")
        params = _validate(stage.params, section.params, path, (*where.split("."), "params"))
        solver = _bind_solver(registry, stage, params, path, where) if stage.solver_kind else None
        inputs = {
            port: dag.parse_ref(text, f"{path}: {where}.inputs.{port}")
            for port, text in section.inputs.items()
        }
        nodes.append(
            dag.Node(
                key,
                stage,
                params,
                solver,
                inputs,
                distribution=distribution(registry, "stages", section.uses),
                solver_distribution=(
                    distribution(registry, "solvers", solver.solver.name) if solver else None
                ),
            )
        )
        wiring[key] = f"{where}.inputs"
    pipeline = dag.build(
        path,
        spec.name,
        nodes,
        wiring,
        description=spec.description,
        device=spec.input.device,
        reader=spec.input.reader,
        raw=raw,
        overrides=overrides,
    )
    calibration = dag.check_export(
        path, spec.export.calibration, pipeline.nodes, "export.calibration", "calibration"
    )
    reports = dag.check_export(path, spec.export.reports, pipeline.nodes, "export.reports", None)
    return dag.Pipeline(
        **{**pipeline.__dict__, "export_calibration": calibration, "export_reports": reports}
    )


def _bind_solver(registry: Registry, stage, params: Params, path: Path, where: str) -> BoundSolver:
    name = getattr(params, "solver", None)
    if not isinstance(name, str):
        raise PluginError(
            f"stage {stage.name!r} has solver_kind {stage.solver_kind!r} but its params "
            "lack a `solver: str` field; fix the stage's Params model"
        )
    solver = _lookup(registry, "solvers", name, path, f"{where}.params.solver")
    if solver.kind != stage.solver_kind:
        same = [
            n
            for n in registry.names("solvers")
            if registry.get("solvers", n).kind == stage.solver_kind
        ]
        raise ConfigError(
            f"{path}: {where}.params.solver: solver {name!r} is of kind {solver.kind!r}; "
            f"stage {stage.name!r} needs kind {stage.solver_kind!r}: "
            f"{', '.join(same) or 'none registered'}"
        )
    raw = getattr(params, "solver_params", None) or {}
    solver_params = _validate(
        solver.params, dict(raw), path, (*where.split("."), "params", "solver_params")
    )
    return BoundSolver(solver, solver_params)


def _lookup(registry: Registry, kind: str, name: str, path: Path, where: str):
    try:
        return registry.get(kind, name)
    except PluginError as exc:
        raise ConfigError(f"{path}: {where}: {exc}") from None


def _validate(model: type[Params], values: dict, path: Path, prefix: tuple) -> Params:
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        raise ConfigError(_message(path, exc, prefix, model)) from None


def _message(path: Path, exc: ValidationError, prefix: tuple, model: type[BaseModel]) -> str:
    """One line: file, key path of the first error, what is wrong (and how many more)."""
    return f"{path}: {describe_validation(exc, model, prefix)}"

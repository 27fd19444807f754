"""Pipeline files (``pipelines/*.toml``): read with tomllib, validated with pydantic.

Every error names the file and the key path, e.g.
``pipelines/x.toml: stages.gyro.params.max_turn_deg: unknown key``. Stage params
are validated by the stage's own ``Params`` model, ``solver_params`` by the
solver's. Nothing here reads data.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..components import BoundSolver, Params
from ..errors import ConfigError, PluginError, describe_validation
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


def resolve_path(path: Path | str | None) -> Path:
    """The pipeline file to use: ``path``, or the default one (an error if it is missing)."""
    if path is None:
        default = default_pipeline_path()
        if not default.is_file():
            raise ConfigError(
                f"{default}: the default pipeline is missing; give one with --pipeline FILE"
            )
        return default
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such pipeline file")
    return path


def load_pipeline(path: Path | str | None, registry: Registry) -> dag.Pipeline:
    """Read, validate and wire a pipeline file (``None``: the default pipeline)."""
    path = resolve_path(path)
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

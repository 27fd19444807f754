"""What a plugin can register: readers, stages, solvers, exporters, executors, effects.

Each kind is a small protocol or frozen dataclass. The host validates what is
registered (see ``plugins.py``); components never touch the plugin manager.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

import pyarrow as pa

if TYPE_CHECKING:
    from .params import Params


_PARAMS = ("Params", "NoParams", "GRAVITY_RANGE_M_S2", "FIELD_RANGE_T", "LocalGravity", "FieldStrength")


def __getattr__(name: str) -> Any:
    """The params names (``params.py``), imported on first use: a command that registers readers
    only (``imupipe ingest``) does not import pydantic."""
    if name in _PARAMS:
        from . import params

        return getattr(params, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# --------------------------------------------------------------------------- readers


@dataclass(frozen=True)
class Recording:
    """What a reader returns: canonical tables per device.

    ``devices`` maps a device name (e.g. the ROS topic namespace ``/imu0``; a
    single-IMU recording uses ``"imu"``) to its streams, keyed by stream name
    (``accel``, ``gyro``, ``mag``, ``temperature``). Every table carries its
    schema id in its schema metadata (``schemas.stamp``).
    """

    source: str
    devices: Mapping[str, Mapping[str, pa.Table]]
    # Session-level facts a reader knows beyond the tables, e.g. ``"sections"``
    # (named protocol sections from a session manifest, see docs/session-manifest.md).
    meta: Mapping[str, Any] = field(default_factory=dict)

    def device(self, name: str | None = None) -> Mapping[str, pa.Table]:
        """The streams of one device; with no name, the only one (or an error naming all)."""
        from .errors import ReaderError

        if name is None:
            if len(self.devices) == 1:
                return next(iter(self.devices.values()))
            raise ReaderError(
                f"{self.source}: holds {len(self.devices)} IMUs ({', '.join(sorted(self.devices))}); "
                "choose one with `device = \"NAME\"` in the pipeline's [input] section, or --device NAME"
            )
        try:
            return self.devices[name]
        except KeyError:
            raise ReaderError(
                f"{self.source}: no device {name!r}; known: {', '.join(sorted(self.devices))}"
            ) from None


@runtime_checkable
class Reader(Protocol):
    """Turns one file into a ``Recording``. After the reader, nothing knows the format.

    Optional: ``delegates(path) -> list[str]``, the other registered readers this
    reader hands parts of ``path`` to (a session manifest's ``reader = ...``);
    their distributions and versions enter the cache key like the reader's own.
    Optional: ``inputs(path) -> list[Path]``, the other files whose bytes make the
    recording (a manifest's data files); their digests enter the cache key.
    """

    name: str
    suffixes: tuple[str, ...]  # lower case, with the dot: (".mcap",)

    def sniff(self, path: Path, head: bytes) -> bool:
        """True if this reader claims the file (``head``: its first 64 bytes)."""

    def read(self, path: Path) -> Recording:
        """Read the whole file; raise ``ReaderError`` naming the file on bad input."""


# --------------------------------------------------------------------------- stages


StageFunc = Callable[[Mapping[str, pa.Table], Any, "BoundSolver | None"], dict[str, pa.Table]]


@dataclass(frozen=True)
class Stage:
    """A pure function of named Arrow tables and a validated params object.

    Called as ``func(inputs, params, solver)``. ``inputs``/``outputs`` map port
    names to schema ids; the runner checks every edge, so ``func`` never
    validates schemas itself. ``optional_inputs`` may be left unwired (absent
    from ``inputs``). Bump ``version`` whenever the outputs for the same inputs
    change: it is part of the cache key.

    A stage with ``solver_kind`` has params with fields ``solver: str`` (a
    registered solver of that kind, with a default) and ``solver_params: dict``;
    the runner looks the solver up, validates ``solver_params`` with the
    solver's own params model, adds the solver's name, version and params to the
    cache key and passes a ``BoundSolver``. Other stages get ``solver=None``.
    """

    name: str
    version: str
    func: StageFunc
    inputs: Mapping[str, str]
    outputs: Mapping[str, str]
    params: type[Params] | None = None  # None: NoParams
    optional_inputs: frozenset[str] = frozenset()
    solver_kind: str | None = None  # when set, params carry `solver` + `solver_params`
    description: str = ""

    def __post_init__(self) -> None:
        if self.params is None:
            from .params import NoParams

            object.__setattr__(self, "params", NoParams)


# --------------------------------------------------------------------------- solvers


@runtime_checkable
class Solver(Protocol):
    """The mathematics of one published method, chosen in config by ``name``.

    A calibrate stage chooses the observations and writes residuals; the solver
    only solves. ``kind`` is the stage family it serves (``thermal``, ``accel``,
    ``mag``, ``gyro``, ``joint``). ``version`` enters the cache key of the stage
    that uses it.
    """

    name: str
    kind: str
    version: str
    params: ClassVar[type[Params]]

    def solve(self, observations: Any, params: Params) -> Any: ...


@dataclass(frozen=True)
class BoundSolver:
    """A solver with its validated params, as a stage receives it."""

    solver: Solver
    params: Params

    def solve(self, observations: Any) -> Any:
        return self.solver.solve(observations, self.params)


# --------------------------------------------------------------------------- exporters


@runtime_checkable
class Exporter(Protocol):
    """Writes results of a run to files (``calibration.json``, reports, ...).

    Optional: ``writes``, the names under ``out_dir`` it writes (files or folders),
    removed when a rerun of the session fails so nothing stale claims success.
    """

    name: str

    def export(self, results: Mapping[str, pa.Table], context: Mapping[str, Any], out_dir: Path) -> list[Path]:
        """Write files under ``out_dir`` atomically; return their paths."""


# --------------------------------------------------------------------------- executors


@runtime_checkable
class Executor(Protocol):
    """Runs independent jobs (one per session in a batch)."""

    name: str

    def map(self, fn: Callable[[Any], Any], items: list[Any], jobs: int) -> list[Any]:
        """Apply ``fn`` to every item; return results in order. ``fn`` must not raise."""


# --------------------------------------------------------------------------- effects


@runtime_checkable
class Effect(Protocol):
    """One omitted-physics effect of ``spec/effects.md``: same face for all.

    ``identifier`` is the first column of the catalogue. The simulator uses
    ``apply``; the diagnosis uses ``regressors`` / ``fit`` / ``explain``.
    """

    identifier: str
    sensor: str  # accel | gyro | mag | temperature | any

    def apply(self, streams: dict[str, Any], truth: Any, parameters: Mapping[str, Any], rng: Any) -> None:
        """Simulator: modify the raw sensor streams in place to include the effect."""


@dataclass(frozen=True)
class Component:
    """A registered component and the plugin that registered it."""

    kind: str
    name: str
    obj: Any
    plugin: str
    distribution: str = ""
    dist_version: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

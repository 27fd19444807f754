"""Fixture plugin for the pipeline tests: a tiny reader, toy stages and a toy solver.

Importable by name (``pipeline_toys``) so batch workers in other processes can
register it too. ``ToyPlugin(...)`` makes variants (stage versions, behaviour)
for the cache tests; the module-level hooks register the default variant.

Sessions are ``.arrowsession`` files: one Arrow IPC table with ``t_ns`` and any
of ``accel_x..z``, ``gyro_x..z``, ``mag_x..z``, ``temperature`` (SI, degC).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np
import pyarrow as pa
from pydantic import Field

from imupipe import schemas
from imupipe.components import Params, Recording, Stage
from imupipe.errors import ReaderError
from imupipe.hookspecs import hookimpl
from imupipe.io import read_arrow, write_arrow
from imupipe.models import TriadCalibration, triads_to_table
from imupipe.pipeline.api import RegistrySpec

TRIADS = ("accel", "gyro", "mag")
# what a batch worker registers: this module, the built-in exporters and executors only
TOY_SPEC = RegistrySpec(
    ("imupipe.exporters", "imupipe.pipeline.executors", "pipeline_toys"), entry_points=False
)
SUFFIX = ".arrowsession"


# --------------------------------------------------------------------------- reader


class ArrowSessionReader:
    name = "arrowsession"
    suffixes = (SUFFIX,)

    def sniff(self, path: Path, head: bytes) -> bool:
        return Path(path).suffix.lower() == SUFFIX

    def read(self, path: Path) -> Recording:
        try:
            table = read_arrow(path)
        except (pa.ArrowInvalid, OSError) as exc:
            raise ReaderError(f"{path}: not an Arrow IPC session ({exc})") from None
        t = table.column("t_ns")
        streams = {}
        for s in TRIADS:
            if f"{s}_x" in table.column_names:
                cols = {"t_ns": t, **{a: table.column(f"{s}_{a}") for a in "xyz"}}
                streams[s] = schemas.stamp(pa.table(cols), s)
        if "temperature" in table.column_names:
            streams["temperature"] = schemas.stamp(
                pa.table({"t_ns": t, "temperature": table.column("temperature")}), "temperature"
            )
        return Recording(str(path), {"imu": streams})


def write_session(
    path: Path,
    streams=("accel", "gyro", "mag", "temperature"),
    seed: int = 0,
    n: int = 200,
    bias: float = 0.1,
) -> Path:
    """A toy session: constant truth + ``bias`` + seeded noise on every triad."""
    rng = np.random.default_rng(seed)
    cols = {"t_ns": np.arange(n, dtype=np.int64) * 10_000_000}
    truth = {"accel": [0.0, 0.0, 9.81], "gyro": [0.0, 0.0, 0.0], "mag": [2e-5, 0.0, 4e-5]}
    for s in TRIADS:
        if s in streams:
            scale = 1e-6 if s == "mag" else 1.0
            values = (
                np.asarray(truth[s]) + bias * scale + 0.01 * scale * rng.standard_normal((n, 3))
            )
            for i, a in enumerate("xyz"):
                cols[f"{s}_{a}"] = values[:, i]
    if "temperature" in streams:
        cols["temperature"] = 25.0 + 0.1 * rng.standard_normal(n)
    write_arrow(path, pa.table(cols))
    return path


# --------------------------------------------------------------------------- solver


class MeanParams(Params):
    scale: float = 1.0


class ToyMeanSolver:
    """Bias = scale * mean of the samples."""

    name = "toy_mean"
    kind = "toy"
    version = "1"
    params = MeanParams

    def solve(self, observations, params: MeanParams):
        return params.scale * np.asarray(observations).mean(axis=0)


class OtherKindSolver(ToyMeanSolver):
    name = "toy_other_kind"
    kind = "other"


# --------------------------------------------------------------------------- stages


class ScaleParams(Params):
    factor: float = 1.0
    label: str = ""  # does not change the output: for early-cutoff tests


class BiasParams(Params):
    solver: str = "toy_mean"
    solver_params: dict = Field(default_factory=dict)
    gravity: Literal["z", "none"] = "z"


def _xyz(table: pa.Table) -> np.ndarray:
    return np.column_stack([table.column(a).to_numpy() for a in "xyz"])


def make_scale(version: str = "1", offset: float = 0.0) -> Stage:
    def scale(inputs, params: ScaleParams, solver):
        t = inputs["samples"]
        xyz = _xyz(t) * params.factor + offset
        out = pa.table({"t_ns": t.column("t_ns"), **{a: xyz[:, i] for i, a in enumerate("xyz")}})
        return {"samples": schemas.stamp(out, "accel")}

    return Stage(
        "toy_scale",
        version,
        scale,
        inputs={"samples": "accel"},
        outputs={"samples": "accel"},
        params=ScaleParams,
    )


def make_bias(sensor: str, version: str = "1") -> Stage:
    def bias(inputs, params: BiasParams, solver):
        mean = solver.solve(_xyz(inputs["samples"]))
        if sensor == "accel" and params.gravity == "z":
            mean = mean - np.array([0.0, 0.0, 9.81])
        details = {"n": inputs["samples"].num_rows, "had_temperature": "temperature" in inputs}
        triad = TriadCalibration(
            sensor, np.eye(3), mean, np.zeros(3), solver=solver.solver.name, details=details
        )
        return {"calibration": triads_to_table([triad])}

    return Stage(
        f"toy_bias_{sensor}",
        version,
        bias,
        inputs={"samples": sensor, "temperature": "temperature"},
        outputs={"calibration": "calibration"},
        params=BiasParams,
        optional_inputs=frozenset({"temperature"}),
        solver_kind="toy",
    )


def _broken(inputs, params, solver):
    return {"wrong": inputs["samples"]}


def _crash(inputs, params, solver):
    """Kills its process on a 13-sample session: what a segfaulting extension would do."""
    if inputs["samples"].num_rows == CRASH_ROWS:
        os._exit(3)
    return {"samples": inputs["samples"]}


CRASH_ROWS = 13
CRASH = Stage("toy_crash", "1", _crash, inputs={"samples": "accel"}, outputs={"samples": "accel"})

BROKEN = Stage(
    "toy_broken", "1", _broken, inputs={"samples": "accel"}, outputs={"samples": "accel"}
)


class ToyPlugin:
    """A variant of the fixture plugin: ``versions``/``offset`` change what the stages are."""

    def __init__(
        self,
        scale_version: str = "1",
        scale_offset: float = 0.0,
        bias_version: str = "1",
        solver_version: str = "1",
    ):
        self.solver = ToyMeanSolver()
        self.solver.version = solver_version
        self.stages = [
            make_scale(scale_version, scale_offset),
            BROKEN,
            CRASH,
            *(make_bias(s, bias_version) for s in TRIADS),
        ]

    @hookimpl
    def imupipe_register_readers(self, register):
        register(ArrowSessionReader())

    @hookimpl
    def imupipe_register_stages(self, register):
        for stage in self.stages:
            register(stage)

    @hookimpl
    def imupipe_register_solvers(self, register):
        register(self.solver)
        register(OtherKindSolver())


_DEFAULT = ToyPlugin()


@hookimpl
def imupipe_register_readers(register):
    _DEFAULT.imupipe_register_readers(register)


@hookimpl
def imupipe_register_stages(register):
    _DEFAULT.imupipe_register_stages(register)


@hookimpl
def imupipe_register_solvers(register):
    _DEFAULT.imupipe_register_solvers(register)


TOY_PIPELINE = """\
name = "toy"
description = "toy stages for the pipeline tests"

[stages.scaled]
uses = "toy_scale"
inputs = { samples = "session.accel" }

[stages.scaled.params]
factor = 1.0

[stages.accel]
uses = "toy_bias_accel"
inputs = { samples = "scaled.samples", temperature = "session.temperature" }

[stages.gyro]
uses = "toy_bias_gyro"
inputs = { samples = "session.gyro" }

[stages.mag]
uses = "toy_bias_mag"
inputs = { samples = "session.mag" }

[stages.mag.params]
solver_params = { scale = 1.0 }

[export]
calibration = ["accel.calibration", "gyro.calibration", "mag.calibration"]
"""


def status_lines(text: str) -> dict[str, str]:
    """stage -> 'state  reasons' from the ``imupipe status`` text of one session."""
    out = {}
    for line in text.splitlines()[1:]:
        state, stage, *rest = line.split(None, 2)
        out[stage] = f"{state} {' '.join(rest)}".strip()
    return out


def write_csv(path: Path, values, rate_hz: float = 100.0, header: str = "t,x,y,z") -> Path:
    """A CSV of time at ``rate_hz`` and the (n, 3) ``values``: ``header`` names the columns.

    Time is in s, or int ns when the first column is ``t_ns`` (the canonical layout).
    """
    ns = header.startswith("t_ns")
    rows = "\n".join(
        f"{round(i * 1e9 / rate_hz) if ns else f'{i / rate_hz:.6g}'},{x:.6f},{y:.6f},{z:.6f}"
        for i, (x, y, z) in enumerate(values)
    )
    Path(path).write_text(f"{header}\n{rows}\n")
    return Path(path)


def write_manifest(path: Path, name: str, *streams: dict) -> Path:
    """A ``session.toml`` naming ``streams`` (each a dict of stream keys: stream, file, ...)."""
    import json

    lines = ["[session]", f"name = {json.dumps(name)}"]
    for stream in streams:
        lines += ["[[streams]]", *(f"{k} = {json.dumps(v)}" for k, v in stream.items())]
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)

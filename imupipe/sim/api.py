"""Simulate a calibration session: in memory (``simulate_recording``) or to files (``simulate``).

``simulate_recording(protocol, effects, seed, imu=None, env=None, **protocol_overrides)``
returns a ``Recording`` (device ``imu``; streams accel, gyro, mag, temperature; raw
SI in the sensor's axes) and its ``Truth``. ``simulate`` writes the recording as
``.mcap`` or canonical ``.csv`` and always ``<out>.truth.json`` beside it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from pydantic import ValidationError

from .. import schemas
from ..components import Recording
from ..errors import ConfigError, describe_validation
from ..io import atomic_path, write_text
from ..progress import progress
from ..writers.mcap import write_mcap
from . import engine, protocols
from .environment import Environment
from .sensor import ImuModel, default_imu
from .trajectory import Rest, Rotate
from .truth import FORMAT_VERSION, Truth, make_truth

T0_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z: the simulated clock's first sample
DEVICE = "imu"
CSV_COLUMNS = ["t_ns", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z",
               "mag_x", "mag_y", "mag_z", "temperature"]


def known_effects(plugins: Iterable[object] = ()) -> dict[str, Any]:
    """Identifier -> effect object: the catalogue (``imupipe.effects``) and every effect a plugin
    registers, installed (entry points) or given in ``plugins`` (one definition of each physics,
    for the simulator and the diagnosis alike)."""
    from ..plugins import make_registry

    registry = make_registry(plugins)
    return {name: registry.get("effects", name) for name in registry.names("effects")}


def resolve_effects(effects: Mapping[str, Mapping[str, Any]] | None, plugins: Iterable[object] = ()
                    ) -> dict[str, tuple[Any, Any]]:
    """Validate ``{identifier: parameters}`` (``known_effects(plugins)``); an unknown identifier lists the known ones.

    ``identifier:tag`` (e.g. ``warmup_transient:accel``) switches on a second instance of the
    same effect, e.g. on another triad.
    """
    catalogue = known_effects(plugins) if effects else {}
    resolved = {}
    for name, params in (effects or {}).items():
        ident = name.split(":", 1)[0]
        if ident not in catalogue:
            raise ConfigError(f"unknown effect {ident!r}; known effects: {', '.join(sorted(catalogue))}")
        effect = catalogue[ident]
        resolved[name] = (effect, effect.validate(params or {}))
    return resolved


def simulate_recording(protocol: str = "standard", effects: Mapping[str, Mapping[str, Any]] | None = None,
                       seed: int = 0, *, imu: ImuModel | Mapping[str, Any] | None = None,
                       env: Environment | Mapping[str, Any] | None = None, plugins: Iterable[object] = (),
                       **protocol_overrides: Any) -> tuple[Recording, Truth]:
    """Simulate ``protocol`` (see ``imupipe.sim.protocols.PROTOCOLS``) with ``effects`` switched on.

    ``imu``: the sensor model (default: realistic consumer-MEMS errors drawn from ``seed``);
    ``env``: the environment (default Moscow); ``plugins``: plugin objects whose effects may be
    switched on besides the installed ones; ``protocol_overrides``: the protocol's parameters.
    The same arguments give the same recording.
    """
    out, truth = simulate_arrays(protocol, effects, seed, imu=imu, env=env, plugins=plugins, **protocol_overrides)
    return _recording(out, f"simulated:{protocol}:seed={seed}"), truth


def simulate_arrays(protocol: str = "standard", effects: Mapping[str, Mapping[str, Any]] | None = None,
                    seed: int = 0, *, imu: ImuModel | Mapping[str, Any] | None = None,
                    env: Environment | Mapping[str, Any] | None = None, plugins: Iterable[object] = (),
                    **protocol_overrides: Any) -> tuple[engine.SimOutput, Truth]:
    """As ``simulate_recording``, but the plain arrays, including the hidden ones: true inputs
    ``inputs[sensor]`` (n, 3) in the instrument frame and the die temperature ``T_die`` (n,)."""
    params = protocols.protocol_params(protocol, **protocol_overrides)
    resolved = resolve_effects(effects, plugins)
    plan = protocols.build(protocol, params, np.random.default_rng([seed, 1]))
    model = _model(imu, np.random.default_rng([seed, 2]))
    if plan.thermal:
        model = model.model_copy(update={"thermal": model.thermal.model_copy(update=plan.thermal)})
    env = _environment(env)
    out = engine.run(plan.trajectory, plan.windows, model, env, resolved, seed)
    truth = make_truth(_truth_dict(protocol, params, seed, model, env, resolved, plan, out))
    truth.data["calibration"] = truth.calibration.to_dict()  # the same, as calibration.json has it
    return out, truth


def simulate(protocol: str, effects: dict[str, dict], seed: int, out: Path, quiet: bool,
             params: Mapping[str, Any] | None = None, imu: Mapping[str, Any] | None = None,
             env: Mapping[str, Any] | None = None, plugins: Iterable[object] = ()) -> list[Path]:
    """Write the simulated session to ``out`` (``.mcap`` or ``.csv``) and ``<out>.truth.json``.

    ``params`` overrides the protocol's parameters (e.g. ``{"n_positions": 60}``), ``imu``
    the sensor model's fields, ``env`` the environment's (e.g. ``{"gravity_m_s2": 9.80665}``),
    ``plugins`` plugin objects with effects beyond the installed ones.
    """
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".mcap", ".csv"):
        raise ConfigError(f"{out}: the simulator writes .mcap or .csv; choose one of those suffixes")
    with progress(quiet) as p:
        task = p.add_task(f"simulating {protocol}", total=2)
        recording, truth = simulate_recording(protocol, effects, seed, imu=imu, env=env, plugins=plugins,
                                              **dict(params or {}))
        p.advance(task)
        if suffix == ".mcap":
            write_mcap(out, recording)
        else:
            write_csv(out, recording)
        truth_path = out.with_name(out.name + ".truth.json")
        write_text(truth_path, truth.to_json())
        p.advance(task)
    return [out, truth_path]


def write_csv(path: Path, recording: Recording) -> None:
    """The canonical CSV layout (``CSV_COLUMNS``; SI, degC), written atomically with polars."""
    import polars as pl

    dev = recording.device(DEVICE)
    cols = {"t_ns": pl.Series(dev["accel"].column("t_ns").to_numpy())}
    for s in ("accel", "gyro", "mag"):
        for ax in "xyz":
            cols[f"{s}_{ax}"] = pl.Series(dev[s].column(ax).to_numpy())
    cols["temperature"] = pl.Series(dev["temperature"].column("temperature").to_numpy())
    with atomic_path(path) as tmp:
        pl.DataFrame(cols).select(CSV_COLUMNS).write_csv(tmp, float_precision=None)


def _model(imu: ImuModel | Mapping[str, Any] | None, rng: np.random.Generator) -> ImuModel:
    if isinstance(imu, ImuModel):
        return imu
    base = default_imu(rng)
    if not imu:
        return base
    try:
        return ImuModel(**{**dict(base), **dict(imu)})
    except ValidationError as exc:
        raise ConfigError(f"imu model: {describe_validation(exc, ImuModel)}") from None


def _environment(env: Environment | Mapping[str, Any] | None) -> Environment:
    if isinstance(env, Environment):
        return env
    try:
        return Environment(**(env or {}))
    except ValidationError as exc:
        raise ConfigError(f"environment: {describe_validation(exc, Environment)}") from None


def _recording(out: engine.SimOutput, source: str) -> Recording:
    t_ns = T0_NS + np.round(out.t * 1e9).astype(np.int64)
    streams = {s: schemas.stamp(pa.table({"t_ns": t_ns, "x": out.raw[s][:, 0], "y": out.raw[s][:, 1],
                                          "z": out.raw[s][:, 2]}), s) for s in ("accel", "gyro", "mag")}
    streams["temperature"] = schemas.stamp(pa.table({"t_ns": t_ns, "temperature": out.temperature}), "temperature")
    return Recording(source=source, devices={DEVICE: streams})


def _truth_dict(protocol, params, seed, model, env, resolved, plan, out) -> dict[str, Any]:
    t_first, t_last = float(out.t[0]), float(out.t[-1])
    segments = []
    for a, b, seg in plan.trajectory.boundaries():
        kind = "rest" if isinstance(seg, Rest) else "turn" if isinstance(seg, Rotate) else "move"
        for w0, w1 in plan.windows:  # only what was recorded: clip to the powered windows
            lo, hi = max(a, w0), min(b, w1, t_last + 1.0 / model.rate_hz)
            if hi > lo and np.any((out.t >= lo) & (out.t < hi)):
                segments.append({"kind": kind, "label": seg.label, "t_start_s": lo - t_first,
                                 "t_end_s": hi - t_first, **_segment_extra(seg)})
    rest_labels = [s["label"] for s in segments if s["kind"] == "rest"]
    refs = {lab: i for i, lab in enumerate(rest_labels) if lab.startswith("reference_")}
    return {
        "format_version": FORMAT_VERSION,
        "seed": seed,
        "protocol": protocol,
        "protocol_params": params.model_dump(),
        "frame": "world ENU (x east, y north, z up); body = instrument frame; attitude body-to-world",
        "model": "y = S x + b0 + turn_on[cycle] + k (T_die - 25) + noise; M = inv(S)",
        "imu": _jsonable(model.model_dump()),
        "environment": env.summary(),
        "effects": {name: p.model_dump() for name, (_, p) in resolved.items()},
        "turn_on_bias": {s: v.tolist() for s, v in out.turn_on.items()},
        "calibration_note": "calibration.b0 = imu.b0 + turn_on_bias[0]",
        "rate_hz": model.rate_hz,
        "t0_ns": T0_NS + round(t_first * 1e9),
        "n_samples": len(out.t),
        "power_windows_s": [[a - t_first, b - t_first] for a, b in plan.windows],
        "temperature_die_C": {"start": float(out.T_die[0]), "end": float(out.T_die[-1]),
                              "min": float(out.T_die.min()), "max": float(out.T_die.max())},
        "segments": segments,
        "reference_rests": refs,
    }


def _segment_extra(seg) -> dict[str, Any]:
    if isinstance(seg, Rotate):
        return {"axis_body": list(seg.unit_axis()), "angle_rad": seg.angle_rad}
    return {}


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, float) and not np.isfinite(obj):
        return None if np.isnan(obj) else ("inf" if obj > 0 else "-inf")
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_jsonable(v) for v in obj]
    return obj


def recording_arrays(recording: Recording, device: str = DEVICE) -> dict[str, np.ndarray]:
    """Plain arrays of a recording: ``t`` (n,) s from the first sample, ``accel``/``gyro``/``mag``
    (n, 3) raw SI, ``temperature`` (n,) degC. Assumes common stamps, as the simulator writes."""
    dev = recording.device(device)
    t_ns = dev["accel"].column("t_ns").to_numpy()
    out = {"t": (t_ns - t_ns[0]) * 1e-9}
    for s in ("accel", "gyro", "mag"):
        if s in dev:
            out[s] = np.column_stack([dev[s].column(ax).to_numpy() for ax in "xyz"])
    out["temperature"] = dev["temperature"].column("temperature").to_numpy()
    return out

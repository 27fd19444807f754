"""The common face of every omitted-physics effect (``components.Effect``).

An effect names itself (``identifier``, the first column of ``spec/effects.md``),
the triads it may act on (``sensors``), the point of the simulator's chain where
it acts (``stage``) and its parameters (a ``Params`` model, SI units). The
simulator calls ``apply(streams, context, parameters, rng)`` once per stage, in
this order, with these arrays in ``streams`` (n samples, times in s from the
first sample):

- ``timing``: ``t_accel`` (n,) the times whose motion the accelerometer sees;
- ``temperature``: ``T_die`` (n,) degC (read-only), ``T_reported`` (n,) degC;
- ``input``: ``accel``/``gyro``/``mag`` (n, 3) the true inputs in the instrument
  frame (specific force at the accelerometer, rate, field), plus read-only
  ``accel_omega``/``accel_alpha`` (n, 3), the body rate and angular acceleration
  at the accelerometer's times, and ``f_body`` (n, 3) the specific force at the
  centre of rotation;
- ``sensed``: ``accel``/``gyro``/``mag`` (n, 3) = ``S x``, in the sensor's axes;
- ``bias``: the same after the nominal bias ``b0 + k (T_die - 25)`` is added;
- ``output``: the same after the white noise is added (before quantisation).

``context`` (``imupipe.sim.engine.SimContext``) holds the trajectory, the
environment, the times ``t`` and time since power-on ``t_on``. Effects never
draw from a shared generator: each gets its own ``rng``, so switching one on
leaves every other random number as it was.

For the diagnosis an effect may also offer ``regressors(inputs, parameters)``
(the columns its term adds to a sensor's residual) and ``explain(parameters)``.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import AfterValidator, ValidationError

from ..components import Params
from ..errors import ConfigError, describe_validation

STAGES = ("timing", "temperature", "input", "sensed", "bias", "output")


def vec3(v: Any) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,):
        raise ValueError(f"expected 3 numbers, got shape {a.shape}")
    return a


def _check3(v: list[float]) -> list[float]:
    if len(v) != 3:
        raise ValueError(f"expected 3 numbers (x, y, z), got {len(v)}")
    return [float(x) for x in v]


def _check33(v: list[list[float]]) -> list[list[float]]:
    if len(v) != 3 or any(len(r) != 3 for r in v):
        raise ValueError("expected a 3x3 matrix (list of 3 rows of 3 numbers)")
    return v


Vec3 = Annotated[list[float], AfterValidator(_check3)]
Mat3 = Annotated[list[list[float]], AfterValidator(_check33)]


class EffectBase:
    """Shared machinery: parameter validation with errors that list the expected fields."""

    identifier: ClassVar[str]
    sensors: ClassVar[tuple[str, ...]]
    stage: ClassVar[str]
    params: ClassVar[type[Params]]
    physics: ClassVar[str]

    @property
    def sensor(self) -> str:
        """The triad (``components.Effect``); ``any`` when ``sensors`` lists several (pick with
        the ``sensor`` parameter)."""
        return self.sensors[0] if len(self.sensors) == 1 else "any"

    def validate(self, parameters: Mapping[str, Any] | Params) -> Params:
        """The parameters as this effect's ``params`` model; ``ConfigError`` lists what it expects."""
        if isinstance(parameters, self.params):
            return parameters
        try:
            return self.params.model_validate(dict(parameters))
        except ValidationError as exc:
            fields = ", ".join(f"{n}: {f.description or f.annotation}" for n, f in self.params.model_fields.items())
            raise ConfigError(
                f"effect {self.identifier}: {describe_validation(exc, self.params)}; expected parameters {{{fields}}}"
            ) from None
        except TypeError as exc:
            raise ConfigError(f"effect {self.identifier}: parameters must be a JSON object ({exc})") from None

    def target(self, p: Params) -> str:
        """The triad this instance acts on."""
        return getattr(p, "sensor", self.sensors[0])

    def apply(self, streams: dict[str, Any], truth: Any, parameters: Mapping[str, Any], rng: Any) -> None:
        self._apply(streams, truth, self.validate(parameters), rng)

    def _apply(self, streams: dict[str, Any], ctx: Any, p: Any, rng: np.random.Generator) -> None:
        raise NotImplementedError

    #: the parameters (in order, flattened) the effect's reading is linear in: ``term`` multiplies
    #: ``regressors`` by them
    linear: ClassVar[tuple[str, ...]] = ()

    def theta(self, p: Params) -> np.ndarray:
        return np.concatenate([np.ravel(np.asarray(getattr(p, name), float)) for name in self.linear])

    def term(self, inputs: Mapping[str, np.ndarray], parameters: Mapping[str, Any] | Params,
             S: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) what the effect adds to its triad's raw reading, to first order: ``regressors``
        times ``theta``; an effect on the true input (``input``/``timing`` stage) goes through
        the triad's ``S``. ``ConfigError`` names a missing input."""
        p = self.validate(parameters)
        if not self.linear or not hasattr(self, "regressors"):
            raise ConfigError(f"effect {self.identifier}: no first-order term to apply")
        try:
            takes_params = len(inspect.signature(self.regressors).parameters) > 1
            R = self.regressors(inputs, p) if takes_params else self.regressors(inputs)
        except KeyError as exc:
            raise ConfigError(f"effect {self.identifier} needs the signal {exc.args[0]!r} (n, 3) or (n,) "
                              "to apply; pass it in signals") from None
        y = np.einsum("nik,k->ni", R, self.theta(p))
        if self.stage in ("input", "timing") and S is not None:
            y = y @ np.asarray(S, float).T
        return y

    def explain(self, parameters: Mapping[str, Any] | Params) -> str:
        p = self.validate(parameters)
        return f"{self.identifier} ({self.target(p)}): {self.physics} Parameters: {p.model_dump()}."

    def __repr__(self) -> str:
        return f"<effect {self.identifier}>"


class ScaleTemperature(EffectBase):
    """Scale factor of each sensor axis is ``1 + s_i (T_die - 25)``, ``s`` in ppm per degC."""

    stage = "sensed"
    linear = ("ppm_per_C",)
    physics = "the scale factor of each axis drifts linearly with die temperature."

    def _apply(self, streams, ctx, p, rng) -> None:
        s = vec3(p.ppm_per_C) * 1e-6
        y = streams[self.sensors[0]]
        streams[self.sensors[0]] = y * (1.0 + np.outer(streams["T_die"] - 25.0, s))

    def regressors(self, inputs: Mapping[str, np.ndarray]) -> np.ndarray:
        """(n, 3, 3): d y / d ppm_per_C given the sensed signal ``x`` (n, 3) and ``T`` (n,) degC."""
        x, dT = np.asarray(inputs["x"]), np.asarray(inputs["T"]) - 25.0
        return np.einsum("ni,ij->nij", x * dT[:, None] * 1e-6, np.eye(3))

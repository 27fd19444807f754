"""The ``estimate_noise`` stage: the recording's own noise model from its longest rests.

Per triad and axis: the overlapping Allan deviation of the ``max_rests`` longest rests of at
least ``min_rest_s`` (pooled per tau; each less its linear dependence on the temperature),
fitted with quantisation, white noise, bias
instability, rate random walk and rate ramp (``imupipe.allan``); per rest, the effective
sample size of its mean under the measured (coloured) noise. A static recording is one long
rest: ``pipelines/noise.toml`` is segmentation and this stage, nothing else.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import numpy as np
import pyarrow as pa
from pydantic import Field

from .. import allan, schemas
from ..components import BoundSolver, Params, Stage
from ..errors import SolverError
from ..models import UNITS
from ..observations import Rests
from .segment import xyz

TRIADS = ("accel", "gyro", "mag")
KALIBR = {"accel": ("accelerometer_noise_density", "accelerometer_random_walk"),
          "gyro": ("gyroscope_noise_density", "gyroscope_random_walk")}


class NoiseParams(Params):
    """``max_rests``: how many of the longest rests are pooled; ``min_rest_s``: shorter rests
    are not used for the Allan curve (they still get an effective sample size);
    ``per_decade``: taus per decade; ``max_tau_fraction``: longest tau as a fraction of a rest;
    ``terms``: the terms fitted (others held at 0); ``detrend_temperature``: remove from each
    rest its linear dependence on the temperature (when wired) before the Allan deviation."""

    max_rests: int = Field(5, ge=1)
    min_rest_s: float = Field(10.0, gt=0)
    per_decade: int = Field(8, ge=2, le=40)
    max_tau_fraction: float = Field(1 / 3, gt=0, le=0.5)
    terms: tuple[str, ...] = allan.TERMS
    detrend_temperature: bool = True


def temperature_free(v: np.ndarray, temp: np.ndarray | None) -> np.ndarray:
    """(n, 3) ``v`` less its least-squares line in the temperature ``temp`` (n,) (a warm-up's
    thermal drift is physics, not noise); ``v`` unchanged without a temperature change."""
    if temp is None or len(v) < 3 or np.ptp(temp) <= 0:
        return v
    A = np.column_stack([np.ones(len(temp)), temp - temp.mean()])
    coef, *_ = np.linalg.lstsq(A, v, rcond=None)
    return v - np.outer(A[:, 1], coef[1])


def _rate(t_ns: np.ndarray) -> float:
    dt = np.diff(t_ns) * 1e-9
    dt = dt[dt > 0]
    if not len(dt):
        raise SolverError("noise: the samples have no increasing stamps; cannot tell the sample rate")
    return float(1.0 / np.median(dt))


def estimate(inputs: Mapping[str, pa.Table], params: NoiseParams, solver: BoundSolver | None) -> dict:
    bad = [t for t in params.terms if t not in allan.TERMS]
    if bad:
        raise SolverError(f"noise: unknown term(s) {bad}; known: {', '.join(allan.TERMS)}")
    rests = Rests.from_table(inputs["rests"])
    dur = rests.t_end_s - rests.t_start_s
    order = [int(i) for i in np.argsort(dur)[::-1] if dur[i] >= params.min_rest_s][: params.max_rests]
    if not order:
        raise SolverError(f"noise: no rest of at least min_rest_s = {params.min_rest_s:g} s (the longest is "
                          f"{dur.max():.1f} s); lower noise.min_rest_s or record a longer still interval")
    t0 = rests.t0_ns
    noise_rows, allan_rows, rest_rows = [], [], []
    doc: dict = {"rests_used": [{"index": i, "t_start_s": float(rests.t_start_s[i]),
                                 "duration_s": float(dur[i])} for i in order],
                 "model": "avar = 3 Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3 + R^2 tau^2/2"}
    for sensor in TRIADS:
        if sensor not in inputs:
            continue
        t_ns, v = xyz(inputs[sensor])
        rate = _rate(t_ns)
        spans = [(np.searchsorted(t_ns, t0 + int(round(a * 1e9)), "left"),
                  np.searchsorted(t_ns, t0 + int(round(b * 1e9)), "right"))
                 for a, b in zip(rests.t_start_s, rests.t_end_s, strict=True)]
        temp = None
        if params.detrend_temperature and "temperature" in inputs:
            tt = inputs["temperature"].column("t_ns").to_numpy()
            temp = np.interp(t_ns.astype(float), tt.astype(float),
                             inputs["temperature"].column("temperature").to_numpy())
        clean = {i: temperature_free(v[spans[i][0]:spans[i][1]],
                                     None if temp is None else temp[spans[i][0]:spans[i][1]])
                 for i in order}
        fits = []
        for k, axis in enumerate("xyz"):
            curve = allan.allan_curve([clean[i][:, k] for i in order], rate,
                                      params.per_decade, params.max_tau_fraction)
            fit = allan.fit_curve(curve, params.terms)
            fits.append(fit)
            c = fit.coef
            noise_rows.append({"sensor": sensor, "axis": axis, "rate_hz": rate, **c,
                               "white_sigma": c["noise_density"] * np.sqrt(rate),
                               "chi2_per_dof": fit.chi2_per_dof, "units": UNITS[sensor],
                               "tau_min_s": float(curve.tau[0]), "tau_max_s": float(curve.tau[-1])})
            for j in range(len(curve.tau)):
                allan_rows.append({"sensor": sensor, "axis": axis, "tau_s": float(curve.tau[j]),
                                   "adev": float(curve.adev[j]), "adev_err": float(curve.adev_err[j]),
                                   "edf": float(curve.edf[j]), "adev_fit": float(fit.adev(curve.tau[j])[0])})
        for i, (a, b) in enumerate(spans):
            seg = v[a:b]
            n = len(seg)
            var = seg.var(axis=0, ddof=1) if n > 1 else np.full(3, np.nan)
            n_eff = [float(allan.effective_sample_size(var[k:k + 1], dur[i:i + 1], np.array([n]), fits[k])[0])
                     if n > 1 else float("nan") for k in range(3)]
            rest_rows.append({"rest": i, "sensor": sensor, "count": n, "duration_s": float(dur[i]),
                              "n_eff": n_eff})
        sd = {t: [f.coef[t] for f in fits] for t in allan.TERMS}
        doc[sensor] = {"rate_hz": rate, "units": UNITS[sensor], **sd,
                       "white_sigma": [x * np.sqrt(rate) for x in sd["noise_density"]]}
        if sensor in KALIBR:
            doc.setdefault("kalibr", {"update_rate": rate, "note": "largest axis"})
            doc["kalibr"][KALIBR[sensor][0]] = max(sd["noise_density"])
            doc["kalibr"][KALIBR[sensor][1]] = max(sd["random_walk"])
    if not noise_rows:
        raise SolverError("noise: the session has no accel, gyro or mag stream")
    meta = {"imupipe.noise": json.dumps(doc), "imupipe.t0_ns": str(t0)}
    n_eff = pa.array([r.pop("n_eff") for r in rest_rows], pa.list_(pa.float64(), 3))
    rest_table = pa.Table.from_pylist(rest_rows).append_column("n_eff", n_eff)
    return {"noise": schemas.stamp(pa.Table.from_pylist(noise_rows), "noise", meta),
            "allan": schemas.stamp(pa.Table.from_pylist(allan_rows), "allan"),
            "rest_noise": schemas.stamp(rest_table, "rest_noise")}


STAGE = Stage(
    name="estimate_noise", version="1", func=estimate,
    inputs={"rests": "rests", "accel": "accel", "gyro": "gyro", "mag": "mag", "temperature": "temperature"},
    outputs={"noise": "noise", "allan": "allan", "rest_noise": "rest_noise"}, params=NoiseParams,
    optional_inputs=frozenset({"accel", "gyro", "mag", "temperature"}),
    description="Allan deviation of the longest rests, fitted (noise density, random walk, ...); "
                "effective sample size per rest",
)
COMPONENTS = [STAGE]

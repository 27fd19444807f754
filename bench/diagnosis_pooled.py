"""`imupipe diagnose SESSION...` pooled: an effect no single session can see, named across sessions.

    python bench/diagnosis_pooled.py [--scenario constant|warmup] [--seeds 3] [--factor 5]
        [--temperatures T ...] [--out DIR]

Per seed, one unit (the consumer-MEMS sensor of ``residual_nulls.realistic_imu``: bias walks,
turn-on bias, quantisation, coarse temperature read-out) is recorded on a short gimbal
protocol once per temperature in ``--temperatures``:

- ``constant`` (default 15 and 45 degC): the die held at that temperature (the unit warm
  before power-on); the effect ``accel_scale_temperature`` (a scale is just a scale at one
  temperature);
- ``warmup`` (default 5 and 35 degC): a cold start at that ambient temperature (the die warms
  by about 9 degC in the session, so each session fits its own ``k``); the effect
  ``bias_temperature_nonlinear`` on the gyro (over one session's narrow range the curvature is
  almost a line, which ``k`` takes; across two ranges with one ``k`` it is not).

First without omitted physics, then with the effect at ``--factor`` times its pooled minimum
detectable size (80 % power at 5 %, from the pooled null's information along the bench's
direction). Every session is diagnosed alone and all are diagnosed pooled
(``imupipe.pipeline.pooled``). Printed: how often the pooled null has any finding (target
<= 5 %), how often a single session and the pooled diagnosis name the effect, its visible
fraction alone and pooled, the fitted size over the true one and the held-out RMS ratio.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from imupipe.diagnosis.select import NONCENTRALITY_80
from imupipe.pipeline.pooled import diagnose_sessions
from imupipe.sim.api import simulate

from diagnosis import SENSOR, direction, effect_params, fitted_size
from residual_nulls import PIPELINE, realistic_imu

SCENARIOS = {"constant": ("accel_scale_temperature", [15.0, 45.0]),
             "warmup": ("bias_temperature_nonlinear", [5.0, 35.0])}
PROTOCOL = {"grid_deg": 45.0, "n_rotations": 30, "rest_s": 3.0}


def sessions(seed: int, scenario: str, temperatures: list[float], effects: dict, folder: Path) -> list[Path]:
    unit = realistic_imu(seed)
    paths = []
    for k, T in enumerate(temperatures):
        ambient = T - unit.thermal.self_heating_C if scenario == "constant" else T
        thermal = unit.thermal.model_copy(update={"ambient_C": ambient, "initial_C": T})
        path = folder / f"unit{seed}-{scenario}{T:g}C-{'-'.join(effects) or 'null'}.mcap"
        simulate("gimbal", effects, 1000 * seed + k, path, quiet=True, params=PROTOCOL,
                 imu=unit.model_copy(update={"thermal": thermal}), env={"gravity_m_s2": 9.80665})
        paths.append(path)
    return paths


def diagnose(paths: list[Path], out: Path) -> tuple[dict, list[dict]]:
    _, pooled = diagnose_sessions(paths, PIPELINE["gimbal"], out, quiet=True)
    single = [json.loads((out / p.stem / "diagnosis.json").read_text()) for p in paths]
    return json.loads(pooled.read_text()), single


def ours(t: dict, effect: str) -> bool:
    return t["effect"] == effect and t["sensor"] == SENSOR.get(effect, "accel")


def visible(doc: dict, effect: str) -> float:
    return max((t["visible_fraction"] for t in doc["tested"] if ours(t, effect)), default=0.0)


def one_seed(seed: int, scenario: str, temperatures: list[float], factor: float, folder: Path) -> dict:
    effect = SCENARIOS[scenario][0]
    folder.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    null, null_single = diagnose(sessions(seed, scenario, temperatures, {}, folder), folder / "out")
    info = next(np.asarray(x["information"]) for x in null["tested"] if ours(x, effect))
    d = direction(effect)
    size = factor * float(np.sqrt(NONCENTRALITY_80 / (d @ info @ d)))
    params = effect_params(effect, size)
    pooled, single = diagnose(sessions(seed, scenario, temperatures, {effect: params}, folder), folder / "out")
    named = [f for f in pooled["findings"] if ours(f, effect)]
    return {
        "seed": seed, "size": size, "seconds": time.perf_counter() - t,
        "null_pooled_findings": [f["effect"] for f in null["findings"]],
        "null_single_findings": [f["effect"] for s in null_single for f in s["findings"]],
        "single_named": [any(ours(f, effect) for f in s["findings"]) for s in single],
        "single_visible": [visible(s, effect) for s in single], "pooled_visible": visible(pooled, effect),
        "pooled_named": bool(named), "pooled_other": [f["effect"] for f in pooled["findings"] if f["effect"] != effect],
        "fitted_over_true": fitted_size(effect, named[0]["parameters"]) / size if named else None,
        "heldout_ratio": named[0]["heldout_rms_after"] / named[0]["heldout_rms_before"] if named else None,
    }


def report(results: list[dict], scenario: str, temperatures: list[float], factor: float) -> None:
    n, effect = len(results), SCENARIOS[scenario][0]
    how = "die held constant" if scenario == "constant" else "cold starts at these ambients"
    print(f"\n{effect} ({SENSOR.get(effect, 'accel')}) at {factor:g}x its pooled minimum detectable size; "
          f"sessions at {', '.join(f'{T:g}' for T in temperatures)} degC ({how}); {n} units")
    print(f"  null, pooled: {sum(bool(r['null_pooled_findings']) for r in results)}/{n} with a finding "
          f"{[r['null_pooled_findings'] for r in results if r['null_pooled_findings']]}")
    print(f"  null, single sessions: {sum(bool(r['null_single_findings']) for r in results)}/{n} units with a finding")
    print(f"  effect named by a single session: {sum(any(r['single_named']) for r in results)}/{n} units "
          f"(visible fraction alone: median {np.median([v for r in results for v in r['single_visible']]):.3f})")
    fo = [r["fitted_over_true"] for r in results if r["fitted_over_true"] is not None]
    ho = [r["heldout_ratio"] for r in results if r["heldout_ratio"] is not None]
    print(f"  effect named pooled: {sum(r['pooled_named'] for r in results)}/{n} units (visible fraction "
          f"pooled: median {np.median([r['pooled_visible'] for r in results]):.3f}; other findings: "
          f"{[r['pooled_other'] for r in results if r['pooled_other']]})")
    print(f"  fitted/true median {np.median(fo) if fo else float('nan'):.3f}, held-out RMS after/before "
          f"median {np.median(ho) if ho else float('nan'):.4f}, size median "
          f"{np.median([r['size'] for r in results]):.3g} (effects.md units)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", choices=sorted(SCENARIOS), default="constant")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--factor", type=float, default=5.0)
    ap.add_argument("--temperatures", type=float, nargs="+", default=None)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    temperatures = args.temperatures or SCENARIOS[args.scenario][1]
    folder = args.out or Path(tempfile.mkdtemp(prefix="diagnosis-pooled-bench-"))
    t = time.perf_counter()
    results = []
    for seed in range(args.seeds):
        try:
            results.append(one_seed(seed, args.scenario, temperatures, args.factor, folder / f"seed{seed}"))
        except Exception as exc:  # noqa: BLE001 - a bench reports failures and goes on
            print(f"  seed {seed} failed: {type(exc).__name__}: {exc}")
    (folder / "diagnosis_pooled.json").write_text(json.dumps(results, indent=1, default=float))
    if results:
        report(results, args.scenario, temperatures, args.factor)
    print(f"\n{args.seeds} seeds in {time.perf_counter() - t:.0f} s; files in {folder}")


if __name__ == "__main__":
    main()

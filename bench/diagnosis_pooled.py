"""`imupipe diagnose SESSION...` pooled: an effect no single session can see, named across sessions.

    python bench/diagnosis_pooled.py [--seeds 3] [--factor 5] [--temperatures 15 45] [--out DIR]

Per seed, one unit (the consumer-MEMS sensor of ``residual_nulls.realistic_imu``: bias walks,
turn-on bias, quantisation, coarse temperature read-out) is recorded on a short gimbal
protocol once per die temperature in ``--temperatures`` (held constant: the unit warm
before power-on), first without omitted physics, then with ``accel_scale_temperature`` at
``--factor`` times its pooled minimum detectable size (80 % power at 5 %, from the pooled
null's information along the bench's direction). Every session is diagnosed alone and all
are diagnosed pooled (``imupipe.pipeline.pooled``). Printed: how often the pooled null has
any finding (target <= 5 %), how often each single session and the pooled diagnosis name the
effect, the effect's visible fraction alone and pooled, the fitted size over the true one
and the held-out RMS ratio.
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

from diagnosis import direction, effect_params, fitted_size
from residual_nulls import PIPELINE, realistic_imu

EFFECT = "accel_scale_temperature"
PROTOCOL = {"grid_deg": 45.0, "n_rotations": 30, "rest_s": 3.0}


def sessions(seed: int, temperatures: list[float], effects: dict, folder: Path) -> list[Path]:
    unit = realistic_imu(seed)
    paths = []
    for k, T in enumerate(temperatures):
        thermal = unit.thermal.model_copy(update={"ambient_C": T - unit.thermal.self_heating_C, "initial_C": T})
        path = folder / f"unit{seed}-{T:g}C-{'-'.join(effects) or 'null'}.mcap"
        simulate("gimbal", effects, 1000 * seed + k, path, quiet=True, params=PROTOCOL,
                 imu=unit.model_copy(update={"thermal": thermal}), env={"gravity_m_s2": 9.80665})
        paths.append(path)
    return paths


def diagnose(paths: list[Path], out: Path) -> tuple[dict, list[dict]]:
    _, pooled = diagnose_sessions(paths, PIPELINE["gimbal"], out, quiet=True)
    single = [json.loads((out / p.stem / "diagnosis.json").read_text()) for p in paths]
    return json.loads(pooled.read_text()), single


def visible(doc: dict) -> float:
    return max((t["visible_fraction"] for t in doc["tested"] if t["effect"] == EFFECT), default=0.0)


def one_seed(seed: int, temperatures: list[float], factor: float, folder: Path) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    null, null_single = diagnose(sessions(seed, temperatures, {}, folder), folder / "out")
    info = next(np.asarray(x["information"]) for x in null["tested"] if x["effect"] == EFFECT)
    d = direction(EFFECT)
    size = factor * float(np.sqrt(NONCENTRALITY_80 / (d @ info @ d)))
    params = effect_params(EFFECT, size)
    pooled, single = diagnose(sessions(seed, temperatures, {EFFECT: params}, folder), folder / "out")
    named = [f for f in pooled["findings"] if f["effect"] == EFFECT]
    return {
        "seed": seed, "size": size, "seconds": time.perf_counter() - t,
        "null_pooled_findings": [f["effect"] for f in null["findings"]],
        "null_single_findings": [f["effect"] for s in null_single for f in s["findings"]],
        "single_named": [any(f["effect"] == EFFECT for f in s["findings"]) for s in single],
        "single_visible": [visible(s) for s in single], "pooled_visible": visible(pooled),
        "pooled_named": bool(named), "pooled_other": [f["effect"] for f in pooled["findings"] if f["effect"] != EFFECT],
        "fitted_over_true": fitted_size(EFFECT, named[0]["parameters"]) / size if named else None,
        "heldout_ratio": named[0]["heldout_rms_after"] / named[0]["heldout_rms_before"] if named else None,
    }


def report(results: list[dict], temperatures: list[float], factor: float) -> None:
    n = len(results)
    print(f"\n{EFFECT} at {factor:g}x its pooled minimum detectable size; sessions at "
          f"{', '.join(f'{T:g}' for T in temperatures)} degC (die held constant); {n} units")
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
          f"{np.median([r['size'] for r in results]):.3g} ppm/degC")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--factor", type=float, default=5.0)
    ap.add_argument("--temperatures", type=float, nargs="+", default=[15.0, 45.0])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    folder = args.out or Path(tempfile.mkdtemp(prefix="diagnosis-pooled-bench-"))
    t = time.perf_counter()
    results = []
    for seed in range(args.seeds):
        try:
            results.append(one_seed(seed, args.temperatures, args.factor, folder / f"seed{seed}"))
        except Exception as exc:  # noqa: BLE001 - a bench reports failures and goes on
            print(f"  seed {seed} failed: {type(exc).__name__}: {exc}")
    (folder / "diagnosis_pooled.json").write_text(json.dumps(results, indent=1, default=float))
    if results:
        report(results, args.temperatures, args.factor)
    print(f"\n{args.seeds} seeds in {time.perf_counter() - t:.0f} s; files in {folder}")


if __name__ == "__main__":
    main()

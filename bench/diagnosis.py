"""`imupipe diagnose` on simulated sessions with one catalogue effect at 5x its minimum detectable size.

    python bench/diagnosis.py [--seeds 3] [--protocols gimbal standard] [--factor 5]
        [--effects lever_arm ...] [--out DIR] [--jobs 1]

For each protocol and seed, a null session (the consumer-MEMS sensor of
``residual_nulls.realistic_imu``: bias walks, turn-on bias, quantisation, a coarse
temperature read-out) is diagnosed first: its ``tested`` list gives each effect's
minimum detectable size on this protocol along the direction the bench uses (80 % power
at 5 %, from the expected information of the term after the nominal model is projected off). Then the same session is simulated with each
effect at ``--factor`` times that size along a fixed direction and diagnosed again. Printed
per protocol and effect: how often the diagnosis names it (target >= 90 %), how often the
residual map's top-ranked cell names its sensor and regime, the fitted size over the true
one, the held-out RMS ratio after/before; and for the nulls how often anything is reported
(target: at most 5 %).

The thermal lag is injected at no less than ``LAG_S`` (four times the temperature smoother's
scale: shorter lags are rejected as read-out artefacts), and at that size where the null says it
cannot be seen: in a first-order warm-up the read-out's rate is affine in its temperature, so the
null's column is absorbed, while a real lag shows as its own start-up after power-on.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from imupipe.diagnosis.select import LAG_MIN_S, NONCENTRALITY_80, VISIBLE_MIN
from imupipe.effects.earth_rotation import EARTH_RATE
from imupipe.pipeline.api import run_sessions
from imupipe.sim.api import simulate

from residual_nulls import PIPELINE, realistic_imu

G = 9.80665
UNIT = np.array([1.0, -1.0, 1.0]) / np.sqrt(3)
G_DIR = np.outer(UNIT, [0.0, 1.0, 1.0]) / np.sqrt(2)  # a unit-norm 3x3 g-sensitivity pattern


def effect_params(effect: str, a: float) -> dict:
    """The effect at size ``a`` along a fixed direction (effects.md parameters)."""
    return {
        "lever_arm": lambda: {"r_m": list(a * UNIT)},
        "accel_gyro_time_offset": lambda: {"dt_s": a},
        "accel_nonlinearity": lambda: {"k2": list(a * UNIT)},
        "accel_scale_temperature": lambda: {"ppm_per_C": list(a * UNIT)},
        "gyro_g_sensitivity": lambda: {"G": (a * G_DIR).tolist()},
        "bias_temperature_nonlinear": lambda: {"k2_per_C2": list(a * UNIT), "sensor": "gyro"},
        "earth_rotation": lambda: {"latitude_deg": float(np.degrees(np.arcsin(min(a / EARTH_RATE, 1.0))))},
        "gyro_scale_temperature": lambda: {"ppm_per_C": list(a * UNIT)},
        "gyro_scale_asymmetry": lambda: {"eps": list(a * UNIT)},
        "thermal_lag": lambda: {"tau_s": a},
        "warmup_transient": lambda: {"amp": list(a * UNIT), "tau_s": WARMUP_TAU_S, "sensor": "gyro"},
    }[effect]()


def fitted_size(effect: str, params: dict) -> float:
    if effect in ("accel_gyro_time_offset", "thermal_lag"):
        return float(params["dt_s" if effect == "accel_gyro_time_offset" else "tau_s"])
    if effect == "gyro_g_sensitivity":
        return float(np.sum(np.asarray(params["G"]) * G_DIR))
    if effect == "earth_rotation":  # the vertical rate Omega sin(lat)
        return EARTH_RATE * float(np.sin(np.radians(params["latitude_deg"])))
    key = {"lever_arm": "r_m", "accel_nonlinearity": "k2", "accel_scale_temperature": "ppm_per_C",
           "bias_temperature_nonlinear": "k2_per_C2", "gyro_scale_temperature": "ppm_per_C",
           "gyro_scale_asymmetry": "eps", "warmup_transient": "amp"}[effect]
    return float(np.asarray(params[key]) @ UNIT)


SENSOR = {"gyro_g_sensitivity": "gyro", "bias_temperature_nonlinear": "gyro", "earth_rotation": "gyro",
          "gyro_scale_temperature": "gyro", "gyro_scale_asymmetry": "gyro", "warmup_transient": "gyro",
          "thermal_lag": None}  # None: either triad (one lag for both, named after the one carrying more)
EFFECTS = ["lever_arm", "accel_gyro_time_offset", "accel_nonlinearity", "accel_scale_temperature",
           "gyro_g_sensitivity", "bias_temperature_nonlinear", "earth_rotation", "gyro_scale_temperature",
           "gyro_scale_asymmetry", "thermal_lag", "warmup_transient"]
MOTION = ("lever_arm", "accel_gyro_time_offset", "gyro_scale_temperature", "gyro_scale_asymmetry")
WARMUP_TAU_S = 120.0  # the injected warm-up transient's time constant (one of select.WARMUP_TAUS_S)
LAG_S = 4 * LAG_MIN_S  # the thermal lag's smallest injected size (shorter ones are read-out artefacts)


def sensor_of(effect: str, sensor: str) -> bool:
    """Whether a tested or named ``sensor`` is the bench's for ``effect``."""
    return SENSOR.get(effect, "accel") in (None, sensor)


def direction(effect: str) -> np.ndarray:
    """The unit direction of ``effect_params`` in the term's parameters (the information's axes)."""
    if effect in ("accel_gyro_time_offset", "earth_rotation", "thermal_lag"):
        return np.ones(1)
    if effect == "gyro_g_sensitivity":
        return G_DIR.ravel()
    return UNIT


def diagnose(protocol: str, seed: int, effects: dict, folder: Path) -> dict:
    path = folder / f"{protocol}-{seed}-{'-'.join(effects) or 'null'}.mcap"
    simulate(protocol, effects, seed, path, quiet=True, imu=realistic_imu(seed), env={"gravity_m_s2": G})
    out = folder / "out"
    t = time.perf_counter()
    run_sessions([path], PIPELINE[protocol], out, quiet=True, diagnose=True)
    doc = json.loads((out / path.stem / "diagnosis.json").read_text())
    rmap = json.loads((out / path.stem / "residual_map.json").read_text())
    doc["top_cell"] = rmap["cells"][0] if rmap["cells"] else None
    doc["seconds"] = time.perf_counter() - t
    return doc


def minimum_detectable(null: dict, effects: list[str]) -> dict[str, float]:
    """Each effect's minimum detectable size along the bench's direction, from a null's ``tested`` list."""
    mde: dict[str, float] = {}
    for t in null["tested"]:
        e = t["effect"]
        if e in effects and t["visible_fraction"] >= VISIBLE_MIN and sensor_of(e, t["sensor"]) \
                and t.get("tau_s", WARMUP_TAU_S) == WARMUP_TAU_S:
            d = direction(e)
            lam = d @ np.asarray(t["information"]) @ d
            mde[e] = min(mde.get(e, np.inf), float(np.sqrt(NONCENTRALITY_80 / lam)) if lam > 0 else np.inf)
    return mde


def injected_size(effect: str, mde: dict[str, float], factor: float) -> float | None:
    """``factor`` x the effect's MDE; None where the protocol cannot see it. A thermal lag the null
    cannot see is still injected, at ``LAG_S``: it shows as its own start-up after power-on."""
    if effect == "thermal_lag":
        return max(factor * mde.get(effect, 0.0), LAG_S)
    m = mde.get(effect, np.inf)
    return factor * m if np.isfinite(m) else None


def regime_of(effect: str) -> str:
    """The residual map's regime where ``effect`` shows (a warm-up shows at rest, along time since power-on)."""
    return "motion" if effect in MOTION else "static"


def top_cell_right(effect: str, cell: dict | None) -> bool:
    """Whether the residual map's top-ranked cell is flagged and names the effect's sensor and regime."""
    return bool(cell and cell["flagged"] and sensor_of(effect, cell["sensor"]) and cell["regime"] == regime_of(effect))


def one_seed(args: tuple[str, int, list[str], float, str]) -> dict:
    protocol, seed, effects, factor, folder = args
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        null = diagnose(protocol, seed, {}, folder)
    except Exception as exc:  # noqa: BLE001 - a bench reports failures and goes on
        return {"protocol": protocol, "seed": seed, "error": str(exc)}
    mde = minimum_detectable(null, effects)
    runs = []
    for e in effects:
        a = injected_size(e, mde, factor)
        if a is None:
            why = [n for n in null["not_identifiable"] if n["effect"] == e and sensor_of(e, n["sensor"])]
            runs.append({"effect": e, "skipped": "not identifiable on this protocol" + (
                f" (visible {why[0]['visible_fraction']:.1%}, absorbed by {', '.join(why[0]['biases'])}; "
                f"reveal with {why[0]['reveal_with']})" if why else "")})
            continue
        try:
            doc = diagnose(protocol, seed, {e: effect_params(e, a)}, folder)
        except Exception as exc:  # noqa: BLE001
            runs.append({"effect": e, "error": str(exc)})
            continue
        named = [f for f in doc["findings"] if f["effect"] == e]
        top = doc["top_cell"]
        runs.append({
            "effect": e, "size": a, "named": bool(named),
            "wrong": [f["effect"] for f in doc["findings"] if f["effect"] not in (e, "unknown")],
            "top_cell_right": top_cell_right(e, top),
            "top_cell": top and f"{top['sensor']}/{top['regime']}/{top['variable']}/{'-'.join(top['axes'])}",
            "fitted_over_true": fitted_size(e, named[0]["parameters"]) / a if named else None,
            "heldout_ratio": (named[0]["heldout_rms_after"] / named[0]["heldout_rms_before"]) if named else None,
            "seconds": doc["seconds"],
        })
    return {"protocol": protocol, "seed": seed, "null_findings": [f["effect"] for f in null["findings"]],
            "mde": mde, "runs": runs, "null_seconds": null["seconds"]}


def report(results: list[dict], factor: float) -> None:
    print(f"\nNULLS: sessions with any finding (target <= 5 %)")
    for proto in sorted({r["protocol"] for r in results}):
        rs = [r for r in results if r["protocol"] == proto and "error" not in r]
        anyf = [r for r in rs if r["null_findings"]]
        catalogue = [r for r in rs if [f for f in r["null_findings"] if f != "unknown"]]
        print(f"  {proto:<10} {len(anyf)}/{len(rs)} with a finding ({len(catalogue)} naming a catalogue effect)"
              + "".join(f"\n    seed {r['seed']}: {r['null_findings']}" for r in anyf))
    print(f"\nEFFECTS at {factor:g}x the minimum detectable size")
    print(f"{'protocol':<10}{'effect':<28}{'runs':>5}{'named':>7}{'wrong name':>11}{'top cell':>9}"
          f"{'fitted/true':>13}{'held-out':>10}{'MDE':>11}")
    for proto in sorted({r["protocol"] for r in results}):
        rs = [r for r in results if r["protocol"] == proto and "error" not in r]
        for e in sorted({x["effect"] for r in rs for x in r["runs"]}):
            xs = [x for r in rs for x in r["runs"] if x["effect"] == e and "named" in x]
            if not xs:
                why = {x.get("skipped") or x.get("error") for r in rs for x in r["runs"] if x["effect"] == e}
                print(f"{proto:<10}{e:<28}  -  {'; '.join(str(w) for w in why)}")
                continue
            fo = [x["fitted_over_true"] for x in xs if x["fitted_over_true"] is not None]
            ho = [x["heldout_ratio"] for x in xs if x["heldout_ratio"] is not None]
            mde = np.median([r["mde"][e] for r in rs if e in r["mde"]] or [np.nan])
            print(f"{proto:<10}{e:<28}{len(xs):>5}{np.mean([x['named'] for x in xs]):>7.0%}"
                  f"{np.mean([bool(x['wrong']) for x in xs]):>11.0%}{np.mean([x['top_cell_right'] for x in xs]):>9.0%}"
                  f"{(np.median(fo) if fo else float('nan')):>13.3f}{(np.median(ho) if ho else float('nan')):>10.4f}"
                  f"{mde:>11.3g}")
    for r in results:
        if "error" in r:
            print(f"  {r['protocol']} seed {r['seed']} failed: {r['error']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--protocols", nargs="+", default=["gimbal", "standard"])
    ap.add_argument("--effects", nargs="+", default=EFFECTS)
    ap.add_argument("--factor", type=float, default=5.0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    folder = args.out or Path(tempfile.mkdtemp(prefix="diagnosis-bench-"))
    jobs = [(p, s, args.effects, args.factor, str(folder / f"{p}-{s}")) for p in args.protocols
            for s in range(args.seeds)]
    t = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(one_seed, jobs))
    (folder / "diagnosis.json").write_text(json.dumps(results, indent=1, default=float))
    report(results, args.factor)
    print(f"\n{len(jobs)} seeds in {time.perf_counter() - t:.0f} s; files in {folder}")


if __name__ == "__main__":
    main()

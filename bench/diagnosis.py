"""`imupipe diagnose` blind on simulated sessions with hidden truths: issue 9's proof benchmark.

    python bench/diagnosis.py [--seeds 3] [--protocols gimbal standard] [--factors 1 2 5]
        [--effects lever_arm ...] [--extra-nulls 0] [--out DIR] [--jobs 1]     (--effects none: nulls only)

Every session has the consumer-MEMS sensor of ``residual_nulls.realistic_imu`` (bias walks,
turn-on bias, quantisation, a coarse temperature read-out): the memo's (§4.1) concealment
"confounded with drift" is in every run. For each protocol and seed, a null session is
diagnosed first: its ``tested`` list gives each effect's minimum detectable size (MDE) on this
protocol along the direction the bench uses (80 % power at 5 %, from the expected information
of the term after the nominal model is projected off). Then the same session is simulated and
diagnosed blind with

- each effect alone at each of ``--factors`` x its MDE (1x and 2x: "under noise"; lever arm,
  time offset and the gyro's scale terms: "invisible at rest"): power (any finding), named,
  wrong names, the residual map's top cell, fitted/true, interval coverage, held-out RMS;
- the naming traps of the memo: Earth's rate against an isotropic g-sensitivity ``G = c I``
  (``gyro_g_sensitivity:isotropic``, injected like an effect), and a warm-up transient, a
  thermal lag and a quadratic bias law among each other. A right answer is the right name or an
  ``unknown`` whose ``parameters.candidates`` name it and a rival (``select._rivals``: a trap
  the recording cannot resolve);
- each effect the null lists ``not_identifiable`` ("absorbed") at a plausible size
  (``TYPICAL``, from the memo's catalogue): a finding naming it is a false discovery, listing it
  ``not_identifiable`` again is the right answer;
- ``PAIRS`` of visible effects at once, each at the largest factor: both named?
- effects outside the catalogue (``outside_catalogue.OUTSIDE``, simulated through the effect
  plugin hook, unknown to the diagnosis): a gyro bias step and a per-axis accelerometer size
  effect, at one fixed size each. A right answer names no catalogue effect (``unknown`` or nothing).

plus ``--extra-nulls`` more null sessions per seed (the memo asks >= 30 % nulls). Printed: the
tables per protocol and a summary with issue 9's targets and PASS/MISS: family-wise false
discoveries on nulls (<= 5 %), power at 2x / 5x MDE (>= 50 % / >= 95 %), naming accuracy among
runs with a catalogue finding (>= 90 %; traps >= 80 %), coverage of the 95 % intervals
``parameters +- 1.96 parameters_sd`` (the memo's §4.3 level; ``parameters_sd`` is the 1-sigma of
the linearised joint fit, per component: each component is one interval) within 90-98 %, the
held-out RMS after/before the fix (``diagnosis.json`` gives RMS in the sensor's units, whitened
for the gyro's scale terms) and the held-out predictive chi2/n after the fix, absorbed effects
(<= 5 % discoveries, >= 80 % correctly ``not_identifiable``). Proportions carry a Clopper-Pearson
95 % interval; PASS/MISS compares the point value with the target.

The thermal lag is injected at no less than ``LAG_S`` (four times the temperature smoother's
scale: shorter lags are rejected as read-out artefacts), and at that size where the null says it
cannot be seen: in a first-order warm-up the read-out's rate is affine in its temperature, so the
null's column is absorbed, while a real lag shows as its own start-up after power-on (so it is
not an "absorbed" case); such a lag is injected once (factor ``-``: not a multiple of an MDE).
The warm-up transient's time constant (``WARMUP_TAU_S``, 75 s) lies between the selection's grid
points (``select.WARMUP_TAUS_S``); it is sized by the nearest one's MDE, and its profiled time
constant counts in the coverage beside its amplitudes.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy import stats

from imupipe.diagnosis.select import LAG_MIN_S, NONCENTRALITY_80, VISIBLE_MIN, WARMUP_TAUS_S
from imupipe.effects.earth_rotation import EARTH_RATE
from imupipe.pipeline.api import run_sessions
from imupipe.sim.api import simulate

import outside_catalogue
from outside_catalogue import OUTSIDE
from residual_nulls import PIPELINE, realistic_imu, session_out, tidy

G = 9.80665
UNIT = np.array([1.0, -1.0, 1.0]) / np.sqrt(3)
G_DIR = np.outer(UNIT, [0.0, 1.0, 1.0]) / np.sqrt(2)  # a unit-norm 3x3 g-sensitivity pattern
ISOTROPIC = "gyro_g_sensitivity:isotropic"  # G = c I: at rest exactly Earth's vertical rate
Z95 = float(stats.norm.ppf(0.975))  # the memo's (§4.3) 95 % parameter intervals


def identifier(name: str) -> str:
    """The catalogue identifier of a bench effect (``identifier:tag``, the simulator's syntax)."""
    return name.split(":", 1)[0]


KEY = {"lever_arm": "r_m", "accel_gyro_time_offset": "dt_s", "accel_nonlinearity": "k2",
       "accel_scale_temperature": "ppm_per_C", "gyro_g_sensitivity": "G", "bias_temperature_nonlinear": "k2_per_C2",
       "earth_rotation": "latitude_deg", "gyro_scale_temperature": "ppm_per_C", "gyro_scale_asymmetry": "eps",
       "thermal_lag": "tau_s", "warmup_transient": "amp"}  # the parameter the bench sizes (effects.md)


def effect_params(effect: str, a: float) -> dict:
    """The effect at size ``a`` along a fixed direction (effects.md parameters); one outside the
    catalogue at its one size (``OUTSIDE``)."""
    if effect in OUTSIDE:
        return OUTSIDE[effect]
    e = identifier(effect)
    if e == "earth_rotation":  # ``a`` the vertical rate Omega sin(lat)
        return {"latitude_deg": float(np.degrees(np.arcsin(min(a / EARTH_RATE, 1.0))))}
    value = a * direction(effect)
    p = {KEY[e]: float(value[0]) if value.size == 1 else
         value.reshape(3, 3).tolist() if value.size == 9 else value.tolist()}
    if e == "bias_temperature_nonlinear":
        p["sensor"] = "gyro"
    if e == "warmup_transient":
        p |= {"tau_s": WARMUP_TAU_S, "sensor": "gyro"}
    return p


def fitted_size(effect: str, params: dict) -> float:
    """The size of fitted ``params`` along the bench's direction (``effect_params``' inverse)."""
    if identifier(effect) == "earth_rotation":  # the vertical rate Omega sin(lat)
        return EARTH_RATE * float(np.sin(np.radians(params["latitude_deg"])))
    return float(np.ravel(params[KEY[identifier(effect)]]) @ direction(effect))


SENSOR = {"gyro_g_sensitivity": "gyro", "bias_temperature_nonlinear": "gyro", "earth_rotation": "gyro",
          "gyro_scale_temperature": "gyro", "gyro_scale_asymmetry": "gyro", "warmup_transient": "gyro",
          "thermal_lag": None}  # None: either triad (one lag for both, named after the one carrying more)
EFFECTS = ["lever_arm", "accel_gyro_time_offset", "accel_nonlinearity", "accel_scale_temperature",
           "gyro_g_sensitivity", "bias_temperature_nonlinear", "earth_rotation", "gyro_scale_temperature",
           "gyro_scale_asymmetry", "thermal_lag", "warmup_transient"]
MOTION = ("lever_arm", "accel_gyro_time_offset", "gyro_scale_temperature", "gyro_scale_asymmetry")
TRAPS = {"earth_rotation": ("gyro_g_sensitivity",), ISOTROPIC: ("earth_rotation",),
         "warmup_transient": ("thermal_lag", "bias_temperature_nonlinear"),
         "thermal_lag": ("warmup_transient", "bias_temperature_nonlinear"),
         "bias_temperature_nonlinear": ("warmup_transient", "thermal_lag")}  # effect: the rivals it is mistaken for
PAIRS = (("lever_arm", "accel_nonlinearity"), ("accel_gyro_time_offset", "gyro_g_sensitivity"),
         ("lever_arm", "earth_rotation"))
TYPICAL = {"gyro_scale_temperature": 300.0,  # ppm/degC: BMI085/088 gyro TCS 0.03 %/K (memo E3)
           "accel_scale_temperature": 20.0,  # ppm/degC: the accelerometer's 0.002 %/K (memo E3)
           "bias_temperature_nonlinear": 1e-6,  # rad/s/degC^2: 0.02 deg/s over a 20 K warm-up (memo E14)
           "gyro_g_sensitivity": 0.1 * np.pi / 180 / G}  # rad/s per m/s^2: BMI088's 0.1 deg/s/g (memo E1)
WARMUP_TAU_S = 75.0  # the injected warm-up transient's time constant: between the selection's grid points
SIZING_TAU_S = min(WARMUP_TAUS_S, key=lambda tau: abs(np.log(tau / WARMUP_TAU_S)))  # its size: from the nearest's MDE
LAG_S = 4 * LAG_MIN_S  # the thermal lag's smallest injected size (shorter ones are read-out artefacts)
NULL_SEEDS = 10_000  # extra null k of seed s is simulated with seed s + k * NULL_SEEDS


def sensor_of(effect: str, sensor: str) -> bool:
    """Whether a tested or named ``sensor`` is the bench's for ``effect``."""
    return SENSOR.get(identifier(effect), "accel") in (None, sensor)


def direction(effect: str) -> np.ndarray:
    """The unit direction of ``effect_params`` in the term's parameters (the information's axes)."""
    if effect == ISOTROPIC:
        return np.eye(3).ravel() / np.sqrt(3)
    if identifier(effect) in ("accel_gyro_time_offset", "earth_rotation", "thermal_lag"):
        return np.ones(1)
    if identifier(effect) == "gyro_g_sensitivity":
        return G_DIR.ravel()
    return UNIT


def mode(effect: str) -> str:
    """The memo's (§4.1) concealment mode the effect is in besides drift and noise."""
    return "naming trap" if effect in TRAPS else "invisible at rest" if effect in MOTION else "-"


def diagnose(protocol: str, seed: int, effects: dict, folder: Path, tag: str = "") -> dict:
    name = "-".join(e.replace(":", "_") for e in effects) or "null"
    path = folder / f"{protocol}-{seed}-{name}{tag}.mcap"
    simulate(protocol, effects, seed, path, quiet=True, imu=realistic_imu(seed), env={"gravity_m_s2": G},
             plugins=[outside_catalogue])
    out = session_out(folder, path)
    t = time.perf_counter()
    run_sessions([path], PIPELINE[protocol], out, quiet=True, diagnose=True)
    doc = json.loads((out / path.stem / "diagnosis.json").read_text())
    rmap = json.loads((out / path.stem / "residual_map.json").read_text())
    doc["top_cell"] = rmap["cells"][0] if rmap["cells"] else None
    doc["seconds"] = time.perf_counter() - t
    truth = json.loads(path.with_name(path.name + ".truth.json").read_text())
    doc["frame"] = calibration_frame(truth, json.loads((out / path.stem / "calibration.json").read_text()))
    tidy(path, out)
    return doc


def calibration_frame(truth: dict, calibration: dict) -> np.ndarray:
    """The rotation from the simulator's body axes to the calibration's: the orthogonal factor of
    ``M_cal inv(M_true)``. The calibration chooses its own frame (a gauge: here 13-19 mrad from the
    body's on gimbal sessions), and the diagnosis reports body-axis vectors in it (a 3 cm lever arm
    is then 0.4-0.6 mm off the simulator's vector, 15-20 of its sd)."""
    M_true = np.linalg.inv(np.asarray(truth["imu"]["accel"]["S"]))
    U, _, Vt = np.linalg.svd(np.asarray(calibration["accel"]["M"]) @ np.linalg.inv(M_true))
    return U @ Vt


def minimum_detectable(null: dict, effects: list[str]) -> dict[str, float]:
    """Each effect's minimum detectable size along the bench's direction, from a null's ``tested`` list."""
    mde: dict[str, float] = {}
    for e in effects:
        for t in null["tested"]:
            if t["effect"] == identifier(e) and t["visible_fraction"] >= VISIBLE_MIN and sensor_of(e, t["sensor"]) \
                    and t.get("tau_s", SIZING_TAU_S) == SIZING_TAU_S:
                d = direction(e)
                lam = d @ np.asarray(t["information"]) @ d
                mde[e] = min(mde.get(e, np.inf), float(np.sqrt(NONCENTRALITY_80 / lam)) if lam > 0 else np.inf)
    return mde


def injected_size(effect: str, mde: dict[str, float], factor: float) -> float | None:
    """``factor`` x the effect's MDE; None where the protocol cannot see it. A thermal lag the null
    cannot see is still injected, at ``LAG_S``: it shows as its own start-up after power-on."""
    m = mde.get(effect, np.inf)
    if effect == "thermal_lag":
        return max(factor * m, LAG_S) if np.isfinite(m) else LAG_S
    return factor * m if np.isfinite(m) else None


def regimes_of(effect: str) -> tuple[str, ...]:
    """The residual map's regimes ``effect`` acts in: the motions only (``MOTION``), or every reading
    (a static term -- Earth's rate, a bias or scale law, a warm-up -- also acts on the samples inside
    motions and on the attitude integrated through them, where a turntable's long turns may show it best)."""
    return ("motion",) if identifier(effect) in MOTION else ("static", "motion")


def top_cell_right(effect: str, cell: dict | None) -> bool:
    """Whether the residual map's top-ranked cell is flagged and names the effect's sensor and a regime it acts in."""
    return bool(cell and cell["flagged"] and sensor_of(effect, cell["sensor"]) and cell["regime"] in regimes_of(effect))


def absorbed(null: dict, effect: str) -> dict | None:
    """The null's ``not_identifiable`` entry for ``effect`` on the bench's sensor, if any."""
    return next((n for n in null["not_identifiable"]
                 if n["effect"] == identifier(effect) and sensor_of(effect, n["sensor"])), None)


def covered(estimate, sd, truth) -> list[bool]:
    """Per component: ``truth`` inside ``estimate +- Z95 sd`` (the 95 % interval)."""
    estimate, sd, truth = (np.ravel(np.asarray(x, float)) for x in (estimate, sd, truth))
    return (np.abs(estimate - truth) <= Z95 * sd).tolist()


BODY_VECTORS = ("lever_arm",)  # parameters that are a vector in body axes (judged in the calibration's frame)


def judged(effect: str, size: float, findings: list[dict], frame: np.ndarray) -> dict:
    """What the diagnosis said of one injected effect: named (on its sensor), fitted/true, coverage
    (a body-axis vector's truth turned into the calibration's ``frame``), held-out."""
    f = next((f for f in findings if f["effect"] == identifier(effect) and sensor_of(effect, f["sensor"])), None)
    ambiguous = [f["parameters"]["candidates"] for f in findings if "candidates" in f["parameters"]]
    out = {"size": size, "named": f is not None,
           "unresolved": any(identifier(effect) in c and set(TRAPS.get(effect, ())) & set(c) for c in ambiguous)}
    if f is None:
        return out
    key = KEY[identifier(effect)]
    sd = f.get("parameters_sd", {}).get(key)
    before, after, z = f["heldout_rms_before"], f["heldout_rms_after"], f["heldout_z"]
    truth = np.asarray(effect_params(effect, size)[key], float)
    if identifier(effect) in BODY_VECTORS:
        truth = frame @ truth
    hit = [] if sd is None else covered(f["parameters"][key], sd, truth)
    if identifier(effect) == "warmup_transient":  # its time constant too (profiled)
        hit += covered(f["parameters"]["tau_s"], f["parameters_sd"].get("tau_s", 0.0), WARMUP_TAU_S)
    return out | {"fitted_over_true": fitted_size(effect, f["parameters"]) / size, "covered": hit,
                  "heldout_ratio": after / before, "heldout_z": z,
                  "heldout_chi2_n": f.get("heldout_chi2_n_after")}


def run(protocol: str, seed: int, kind: str, sizes: dict[str, float], factor: float | None, folder: Path,
        sim_seed: int | None = None) -> dict:
    """One blind diagnosis of ``sizes`` (effect: size) injected; ``kind``: effect, trap, absorbed, pair,
    outside, null."""
    rec = {"kind": kind, "protocol": protocol, "seed": seed, "sim_seed": seed if sim_seed is None else sim_seed,
           "factor": factor, "sizes": sizes}
    tag = "" if factor is None else f"-{factor:g}x"
    try:
        doc = diagnose(protocol, seed if sim_seed is None else sim_seed,
                       {e: effect_params(e, a) for e, a in sizes.items()}, folder, tag)
    except Exception as exc:  # noqa: BLE001 - a bench reports failures and goes on
        return rec | {"error": str(exc)}
    top = doc["top_cell"]
    return rec | {
        "findings": [f["effect"] for f in doc["findings"]], "seconds": doc["seconds"],
        "candidates": [f["parameters"]["candidates"] for f in doc["findings"] if "candidates" in f["parameters"]],
        "effects": {e: judged(e, a, doc["findings"], doc["frame"]) for e, a in sizes.items()},
        "not_identifiable": [e for e in sizes if absorbed(doc, e)],
        "top_cell_right": len(sizes) == 1 and top_cell_right(next(iter(sizes)), top),
        "top_cell": top and f"{top['sensor']}/{top['regime']}/{top['variable']}/{'-'.join(top['axes'])}"}


def plan(null: dict, effects: list[str], factors: list[float]) -> list[tuple[str, dict[str, float], float | None]]:
    """The seed's blind runs: ``(kind, {effect: size}, factor)``."""
    mde = minimum_detectable(null, effects)
    runs = []
    for e in effects:  # one not sized by an MDE (a lag the null cannot see) once, at its own size
        sizes = {f: injected_size(e, mde, f) for f in factors} if np.isfinite(mde.get(e, np.inf)) \
            else {None: injected_size(e, mde, 1.0)}
        runs += [("trap" if e in TRAPS else "effect", {e: a}, f) for f, a in sizes.items() if a is not None]
    runs += [("absorbed", {e: TYPICAL[e]}, None) for e in effects
             if injected_size(e, mde, 1.0) is None and absorbed(null, e) and e in TYPICAL]
    top = max(factors)
    runs += [("pair", {e: injected_size(e, mde, top) for e in pair}, top) for pair in PAIRS
             if all(e in effects and injected_size(e, mde, top) is not None for e in pair)]
    runs += [("outside", {e: 1.0}, None) for e in OUTSIDE if e in effects]
    return runs


def one_seed(args: tuple[str, int, list[str], list[float], int, str]) -> dict:
    protocol, seed, effects, factors, extra_nulls, folder = args
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    try:
        null = diagnose(protocol, seed, {}, folder)
    except Exception as exc:  # noqa: BLE001
        return {"protocol": protocol, "seed": seed, "error": str(exc)}
    runs = [{"kind": "null", "protocol": protocol, "seed": seed, "sim_seed": seed, "factor": None, "sizes": {},
             "effects": {}, "findings": [f["effect"] for f in null["findings"]], "candidates": [],
             "seconds": null["seconds"]}]
    runs += [run(protocol, seed, "null", {}, None, folder, seed + k * NULL_SEEDS) for k in range(1, extra_nulls + 1)]
    runs += [run(protocol, seed, kind, sizes, f, folder) for kind, sizes, f in plan(null, effects, factors)]
    skipped = {e: absorbed(null, e) for e in effects if e not in {x for r in runs for x in r["sizes"]}}
    return {"protocol": protocol, "seed": seed, "mde": minimum_detectable(null, effects), "runs": runs,
            "skipped": skipped, "seconds": time.perf_counter() - t}


def ratio(hits: list[bool]) -> tuple[int, int]:
    return int(sum(hits)), len(hits)


def share(k: int, n: int) -> str:
    """``k/n  p % [lo-hi]``, the Clopper-Pearson 95 % interval."""
    if not n:
        return "0/0"
    ci = stats.binomtest(k, n).proportion_ci(0.95)
    return f"{k}/{n} {k / n:.0%} [{ci.low:.0%}-{ci.high:.0%}]"


def verdict(value: float, lo: float = -np.inf, hi: float = np.inf) -> str:
    """PASS or MISS of ``value`` against ``[lo, hi]``; ``-`` without a value or a target."""
    if not np.isfinite(value) or (lo, hi) == (-np.inf, np.inf):
        return "-"
    return "PASS" if lo <= value <= hi else "MISS"


def answered(x: dict) -> bool:
    """Whether a run names catalogue effects: a catalogue finding or an ``unknown`` naming candidates."""
    return any(f != "unknown" for f in x["findings"]) or bool(x["candidates"])


def right(x: dict, e: str) -> bool:
    """The injected effect named, or (a trap) an ``unknown`` naming it and a rival."""
    return x["effects"][e]["named"] or x["effects"][e]["unresolved"]


def wrong(x: dict) -> list[str]:
    """Catalogue names of a run that none of its injected effects has."""
    return [f for f in x["findings"] if f not in ("unknown", *map(identifier, x["sizes"]))]


def pct(value: float) -> str:
    return f"{value:.0%}" if np.isfinite(value) else "-"


def median(values: list) -> float:
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else float("nan")


def of_median(values: list) -> str:
    """``median over n``; ``-`` without values."""
    return f"{median(values):.4f} over {len(values)}" if values else "-"


def report(results: list[dict]) -> dict[str, tuple[str, str, str]]:
    """Print the tables; return the summary (criterion: measured, target, verdict)."""
    runs = [x for r in results if "runs" in r for x in r["runs"] if "error" not in x]
    protocols = sorted({x["protocol"] for x in runs})
    nulls = [x for x in runs if x["kind"] == "null"]
    print("\nNULLS: sessions with any finding (target <= 5 %)")
    for proto in protocols:
        ns = [x for x in nulls if x["protocol"] == proto]
        anyf = [x for x in ns if x["findings"]]
        print(f"  {proto:<10} {share(*ratio([bool(x['findings']) for x in ns]))} with a finding "
              f"({sum(answered(x) for x in ns)} naming a catalogue effect)"
              + "".join(f"\n    seed {x['sim_seed']}: {x['findings']}" for x in anyf))
    print("\nEFFECTS alone at factor x their minimum detectable size (power: any finding; right: of runs naming "
          "catalogue effects, the injected one, or for a trap an unknown naming it and a rival)")
    print(f"{'protocol':<10}{'effect':<30}{'x':>4}{'runs':>5}{'power':>7}{'named':>7}{'right':>7}{'wrong':>7}"
          f"{'top':>6}{'fit/true':>9}{'cover':>8}{'held-out':>9}{'MDE':>10}  mode")
    single = [x for x in runs if x["kind"] in ("effect", "trap")]
    for proto in protocols:
        mde = [r["mde"] for r in results if r.get("protocol") == proto and "mde" in r]
        for e in dict.fromkeys(e for x in single if x["protocol"] == proto for e in x["sizes"]):
            for f in sorted({x["factor"] for x in single}, key=lambda f: -1 if f is None else f):
                xs = [x for x in single if x["protocol"] == proto and e in x["sizes"] and x["factor"] == f]
                if not xs:
                    continue
                js = [x["effects"][e] for x in xs]
                cov = [c for j in js for c in j.get("covered", [])]
                ans = [x for x in xs if answered(x)]
                print(f"{proto:<10}{e:<30}{'-' if f is None else f'{f:g}':>4}{len(xs):>5}{np.mean([bool(x['findings']) for x in xs]):>7.0%}"
                      f"{np.mean([j['named'] for j in js]):>7.0%}"
                      f"{pct(np.mean([right(x, e) for x in ans]) if ans else np.nan):>7}"
                      f"{np.mean([bool(wrong(x)) for x in xs]):>7.0%}{np.mean([x['top_cell_right'] for x in xs]):>6.0%}"
                      f"{median([j.get('fitted_over_true') for j in js]):>9.3f}"
                      f"{(f'{sum(cov)}/{len(cov)}' if cov else '-'):>8}"
                      f"{median([j.get('heldout_ratio') for j in js]):>9.4f}"
                      f"{median([m.get(e) for m in mde]):>10.3g}  {mode(e)}")
    for r in results:
        for e, why in r.get("skipped", {}).items():
            print(f"{r['protocol']:<10}{e:<30}  seed {r['seed']}: not injected, not identifiable"
                  + (f" (visible {why['visible_fraction']:.1%}, absorbed by {', '.join(why['biases'][:3])}; no "
                     f"typical size in TYPICAL)" if why else ""))
    print("\nABSORBED: effects the null lists not_identifiable, at a typical size (targets: discovered <= 5 %, "
          "listed not_identifiable >= 80 %)")
    for x in (x for x in runs if x["kind"] == "absorbed"):
        (e, a), = x["sizes"].items()
        print(f"  {x['protocol']:<10}{e:<30}{a:>10.3g}  seed {x['seed']}: discovered {x['effects'][e]['named']}, "
              f"not_identifiable {e in x['not_identifiable']}, findings {x['findings']}")
    print("\nOUTSIDE the catalogue (simulated by a plugin the diagnosis does not know): right = no catalogue name")
    for x in (x for x in runs if x["kind"] == "outside"):
        print(f"  {x['protocol']:<10}{next(iter(x['sizes'])):<30} seed {x['seed']}: findings {x['findings']}, "
              f"right {not wrong(x)}")
    print("\nPAIRS at the largest factor: both named")
    for x in (x for x in runs if x["kind"] == "pair"):
        print(f"  {x['protocol']:<10}{' + '.join(x['sizes']):<50} seed {x['seed']}: "
              f"both {all(j['named'] for j in x['effects'].values())}, findings {x['findings']}")
    for r in results:
        for x in [r] if "error" in r else [x for x in r["runs"] if "error" in x]:
            print(f"  {x['protocol']} seed {x['seed']} {x.get('kind', 'null')} {list(x.get('sizes', {}))} "
                  f"failed: {x['error']}")
    return summary(runs)


def summary(runs: list[dict]) -> dict[str, tuple[str, str, str]]:
    """Issue 9's criteria over ``runs`` (records of ``run``): criterion -> (measured, target, verdict)."""
    def of(kind: str, factor: float | None = None) -> list[dict]:
        return [x for x in runs if x["kind"] in kind.split("|") and factor in (None, x["factor"])]

    def one(xs: list[dict]) -> list[tuple[dict, str]]:
        return [(x, e) for x in xs for e in x["sizes"]]

    def rate(hits: list[bool], lo: float = -np.inf, hi: float = np.inf, target: str = "-") -> tuple[str, str, str]:
        k, n = ratio(hits)
        return share(k, n), target, verdict(k / n if n else np.nan, lo, hi)

    named = [x["effects"][e] for x, e in one(of("effect|trap")) if x["effects"][e]["named"]]
    chi2_n = [j["heldout_chi2_n"] for j in named if j["heldout_chi2_n"] is not None]
    return {
        "nulls: family-wise false discoveries": rate([bool(x["findings"]) for x in of("null")], hi=0.05,
                                                     target="<= 5 %"),
        "nulls: share of sessions": rate([x["kind"] == "null" for x in runs], lo=0.30, target=">= 30 %"),
        "power at 2x MDE": rate([bool(x["findings"]) for x in of("effect|trap", 2.0)], lo=0.50, target=">= 50 %"),
        "power at 5x MDE": rate([bool(x["findings"]) for x in of("effect|trap", 5.0)], lo=0.95, target=">= 95 %"),
        "naming accuracy": rate([right(x, e) for x, e in one(of("effect")) if answered(x)], lo=0.90,
                                target=">= 90 %"),
        "naming accuracy, traps": rate([right(x, e) for x, e in one(of("trap")) if answered(x)], lo=0.80,
                                       target=">= 80 %"),
        "95 % interval coverage": rate([c for j in named for c in j["covered"]], 0.90, 0.98, "90-98 %"),
        "held-out RMS after/before (median)": (of_median([j["heldout_ratio"] for j in named]), "< 1",
                                               verdict(median([j["heldout_ratio"] for j in named]), hi=1.0)),
        "held-out predictive chi2/n after (median)": (of_median(chi2_n), "-", "-"),
        "absorbed: discoveries": rate([x["effects"][e]["named"] for x, e in one(of("absorbed"))], hi=0.05,
                                      target="<= 5 %"),
        "absorbed: any finding (also unknown)": rate([bool(x["findings"]) for x in of("absorbed")]),
        "absorbed: listed not_identifiable": rate([e in x["not_identifiable"] for x, e in one(of("absorbed"))],
                                                  lo=0.80, target=">= 80 %"),
        "pairs: both named": rate([all(j["named"] for j in x["effects"].values()) for x in of("pair")]),
        "outside: found (any finding)": rate([bool(x["findings"]) for x in of("outside")]),
        "outside: no catalogue name": rate([not wrong(x) for x in of("outside")], lo=0.95, target=">= 95 %"),
    }


def print_summary(rows: dict[str, tuple[str, str, str]]) -> None:
    print(f"\nSUMMARY (issue 9)\n{'criterion':<40}{'measured':<28}{'target':<10}verdict")
    for name, (value, target, ok) in rows.items():
        print(f"{name:<40}{value:<28}{target:<10}{ok}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--protocols", nargs="+", default=["gimbal", "standard"])
    ap.add_argument("--effects", nargs="+", default=EFFECTS + [ISOTROPIC, *OUTSIDE], help="'none': nulls only")
    ap.add_argument("--factors", nargs="+", type=float, default=[1.0, 2.0, 5.0])
    ap.add_argument("--extra-nulls", type=int, default=0, help="more null sessions per seed")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    effects = [e for e in args.effects if e != "none"]
    folder = args.out or Path(tempfile.mkdtemp(prefix="diagnosis-bench-"))
    jobs = [(p, s, effects, args.factors, args.extra_nulls, str(folder / f"{p}-{s}")) for p in args.protocols
            for s in range(args.first_seed, args.first_seed + args.seeds)]
    t = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(one_seed, jobs))
    (folder / "diagnosis.json").write_text(json.dumps(results, indent=1, default=float))
    print_summary(report(results))
    for proto in args.protocols:
        rs = [r for r in results if r["protocol"] == proto and "runs" in r]
        per_run = median([x.get("seconds") for r in rs for x in r["runs"]])
        print(f"{proto}: {median([r['seconds'] for r in rs]):.0f} s per seed "
              f"({median([len(r['runs']) for r in rs]):.0f} sessions, {per_run:.0f} s per diagnosis "
              "without its simulation)")
    print(f"\n{len(jobs)} seeds in {time.perf_counter() - t:.0f} s; files in {folder}")


if __name__ == "__main__":
    main()

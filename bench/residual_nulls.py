"""The residual map on simulated sessions: silent on nulls, pointing at the right cell when physics is missing.

    python bench/residual_nulls.py [--seeds 20] [--protocols standard sphere_rig gimbal]
        [--effects [--effect-seeds 5] [--only EFFECT ...]] [--instability] [--out DIR] [--jobs 2]
                                                              (--seeds 0: the effects only)

Nulls: ``--seeds`` sessions of each protocol with the simulator's consumer-MEMS model
(white noise, quantisation, turn-on bias, thermal drift) plus a bias random walk on
both triads (1e-5 m/s^2/sqrt(s), 1e-6 rad/s/sqrt(s)) and a coarse temperature
read-out (0.125 degC, a BMI088's), through the protocol's pipeline (``standard`` and
``sphere_rig``: the default pipeline; ``gimbal``: gimbal-optimization); every
``residual_map.json`` is read and the bench prints, per protocol, the share of runs
whose every block has chi2/dof within 1 +- 3 sqrt(2/dof) (target >= 90 %) and the
share with no cell flagged at BH q = 0.05 (target >= 95 %), with each block's median
chi2/dof.

``--instability``: the nulls' sensor also has a bias instability (``INSTABILITY``, first-order
Gauss-Markov: what real parts have beside a walk, and what another simulator may draw), which
the model takes as a walk: a robustness check of the nulls, not a null of the model.

``--effects`` (after the nulls): each catalogue effect the protocol can see, at
5x its minimum detectable size (from the expected information of seed 0's null
diagnosis, ``bench/diagnosis.py``'s ``minimum_detectable``), on ``--effect-seeds``
sessions each, and the share of runs whose top-ranked cell is flagged and names the
effect's sensor and a regime it acts in (``diagnosis.regimes_of``; target >= 90 %).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from imupipe.pipeline.api import run_sessions
from imupipe.sim.api import simulate
from imupipe.sim.sensor import default_imu

REPO = Path(__file__).resolve().parents[1]
G = 9.80665
PIPELINE = {"standard": None, "sphere_rig": None, "gimbal": REPO / "pipelines" / "gimbal-optimization.toml",
            "ferraris": REPO / "pipelines" / "ferraris.toml"}
BAND_SD = 3.0
# a bias instability of the size consumer MEMS data sheets give (gyro ~4 deg/h, accelerometer ~20 ug),
# as a first-order Gauss-Markov process over 100 s
INSTABILITY = {"accel": {"bias_gm_sd": 2e-4, "bias_gm_tau_s": 100.0},
               "gyro": {"bias_gm_sd": 2e-5, "bias_gm_tau_s": 100.0}}


def realistic_imu(seed: int, instability: bool = False):
    """The consumer-MEMS sensor of the benches; ``instability``: plus a bias instability the
    model does not have (``INSTABILITY``: Gauss-Markov, not a walk)."""
    imu = default_imu(np.random.default_rng([seed, 2]))
    extra = INSTABILITY if instability else {"accel": {}, "gyro": {}}
    return imu.model_copy(update={
        "accel": imu.accel.model_copy(update={"bias_rw": 1e-5, **extra["accel"]}),
        "gyro": imu.gyro.model_copy(update={"bias_rw": 1e-6, **extra["gyro"]}),
        "thermal": imu.thermal.model_copy(update={"readout_quantum_C": 0.125}),
    })


def one_run(args: tuple[str, int, dict, str, bool]) -> dict:
    protocol, seed, effects, folder, instability = args
    folder = Path(folder)
    path = folder / f"{protocol}-{seed}-{'-'.join(effects) or 'null'}.mcap"
    simulate(protocol, effects, seed, path, quiet=True, imu=realistic_imu(seed, instability),
             env={"gravity_m_s2": G})
    out = session_out(folder, path)
    t = time.perf_counter()
    try:
        run_sessions([path], PIPELINE[protocol], out, quiet=True)
    except Exception as exc:  # noqa: BLE001 - a bench reports failures and goes on
        return {"protocol": protocol, "seed": seed, "effects": effects, "error": str(exc)}
    doc = json.loads((out / path.stem / "residual_map.json").read_text())
    tidy(path, out)
    return {"protocol": protocol, "seed": seed, "effects": effects, "seconds": time.perf_counter() - t,
            "blocks": doc["blocks"], "flagged": [c for c in doc["cells"] if c["flagged"]],
            "top": doc["cells"][0] if doc["cells"] else None, "events": doc["events"]}


def session_out(folder: Path, path: Path) -> Path:
    """The out folder of one simulated session: its own, so that ``tidy``ing its cache cannot pull
    another job's from under it (a shared cache did so with two jobs)."""
    return Path(folder) / "out" / path.stem


def tidy(path: Path, out: Path) -> None:
    """Keep a run's documents, not its bulk (the recording, the per-sample table, the cache:
    ~100 MB a session; hundreds of sessions fill a disk)."""
    path.unlink(missing_ok=True)
    (out / path.stem / "residuals.parquet").unlink(missing_ok=True)
    shutil.rmtree(out / ".cache", ignore_errors=True)


def in_band(block: dict) -> bool:
    if not block["dof"] or block["chi2_per_dof"] is None:
        return True
    return abs(block["chi2_per_dof"] - 1) <= BAND_SD * np.sqrt(2 / block["dof"])


def report_nulls(results: list[dict]) -> None:
    print("\nNULLS (no omitted physics): blocks in 1 +- 3 sqrt(2/dof) and cells flagged at BH q = 0.05")
    print(f"{'protocol':<12}{'runs':>5}{'all blocks in band':>20}{'no cell flagged':>17}   median chi2/dof per block")
    for proto in sorted({r["protocol"] for r in results}):
        rs = [r for r in results if r["protocol"] == proto and "blocks" in r]
        failed = sum(1 for r in results if r["protocol"] == proto and "error" in r)
        if not rs:
            print(f"{proto:<12}{0:>5}  (all {failed} runs failed)")
            continue
        band = np.mean([all(in_band(b) for b in r["blocks"]) for r in rs])
        quiet = np.mean([not r["flagged"] for r in rs])
        names = sorted({b["block"] for r in rs for b in r["blocks"]})
        med = "  ".join(f"{n} {np.median([b['chi2_per_dof'] for r in rs for b in r['blocks'] if b['block'] == n and b['chi2_per_dof'] is not None]):.3f}"
                        for n in names)
        print(f"{proto:<12}{len(rs):>5}{band:>19.0%}{quiet:>17.0%}   {med}"
              + (f"  ({failed} failed)" if failed else ""))
        for r in rs:
            bad = [f"{b['block']} {b['chi2_per_dof']:.3f} (dof {b['dof']:.0f})" for b in r["blocks"] if not in_band(b)]
            flags = [f"{c['sensor']}/{','.join(c['axes'])}/{c['regime']}/{c['variable']} {c['chi2_per_dof']:.2f}"
                     for c in r["flagged"][:3]]
            if bad or flags:
                print(f"    seed {r['seed']}: " + "; ".join(bad + flags))
    print("targets: all blocks in band >= 90 % of runs; no cell flagged >= 95 % of runs")


def effect_runs(protocols: list[str], seeds: int, folder: Path, jobs: int, only: list[str] | None = None) -> None:
    import diagnosis as dg  # the effects' sizes and directions (it imports this module: import here)

    print(f"\nEFFECTS at 5x the minimum detectable size: top-ranked cell flagged, on the right sensor and regime")
    print(f"{'protocol':<12}{'effect':<28}{'runs':>5}{'top cell right':>16}   wrong top cells")
    for proto in protocols:
        (folder / f"{proto}-mde").mkdir(parents=True, exist_ok=True)
        mde = dg.minimum_detectable(dg.diagnose(proto, 0, {}, folder / f"{proto}-mde"), dg.EFFECTS)
        sized = {e: dg.injected_size(e, mde, 5.0) if np.isfinite(mde.get(e, np.inf)) else None
                 for e in dg.EFFECTS if not only or e in only}
        runs = [(proto, s, {e: dg.effect_params(e, a)}, str(folder / f"{proto}-{e}-{s}"), False)
                for e, a in sized.items() if a is not None for s in range(seeds)]
        with ProcessPoolExecutor(jobs) as pool:
            results = list(pool.map(one_run, runs))
        (folder / f"effects-{proto}.json").write_text(json.dumps(results, indent=1))
        for e, a in sized.items():
            if a is None:
                print(f"{proto:<12}{e:<28}    -   not identifiable on this protocol (no finite MDE)")
                continue
            rs = [r for r in results if e in r["effects"]]
            right = [dg.top_cell_right(e, r.get("top")) for r in rs]
            wrong = [f"seed {r['seed']}: " + (r["error"] if "error" in r else
                     "none flagged" if not (r["top"] and r["top"]["flagged"]) else
                     f"{r['top']['sensor']}/{r['top']['regime']}/{r['top']['variable']}")
                     for r, ok in zip(rs, right) if not ok]
            print(f"{proto:<12}{e:<28}{len(rs):>5}{np.mean(right):>16.0%}   {'; '.join(wrong)}")
    print("target: top cell right >= 90 % of runs")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--protocols", nargs="+", default=["standard", "sphere_rig", "gimbal"])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--effects", action="store_true")
    ap.add_argument("--effect-seeds", type=int, default=5)
    ap.add_argument("--only", nargs="+", default=None, help="these effects of the catalogue only")
    ap.add_argument("--instability", action="store_true",
                    help="nulls with a bias instability the model does not have (INSTABILITY)")
    args = ap.parse_args()
    folder = args.out or Path(tempfile.mkdtemp(prefix="residual-nulls-"))
    folder.mkdir(parents=True, exist_ok=True)
    if args.seeds:
        jobs = [(p, s, {}, str(folder / f"{p}-{s}"), args.instability) for p in args.protocols
                for s in range(args.seeds)]
        t = time.perf_counter()
        with ProcessPoolExecutor(args.jobs) as pool:
            results = list(pool.map(one_run, jobs))
        (folder / "nulls.json").write_text(json.dumps(results, indent=1))
        report_nulls(results)
        secs = [r["seconds"] for r in results if "seconds" in r]
        print(f"\n{len(results)} runs in {time.perf_counter() - t:.0f} s (pipeline {np.median(secs):.1f} s median per run); "
              f"files in {folder}")
    if args.effects:
        effect_runs(args.protocols, args.effect_seeds, folder, args.jobs, args.only)


if __name__ == "__main__":
    main()

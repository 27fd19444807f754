"""`imupipe diagnose` on null sessions under variations another simulator may use.

    python bench/diagnosis_variants.py [--seeds 2] [--variants NAME ...] [--jobs 2]

Each variant is a null (no omitted physics) of the benches' consumer-MEMS sensor
(``residual_nulls.realistic_imu``) with one thing changed: rests of 2 s (``gimbal-rest2``,
``standard-rest2``), a 200 Hz sensor (``gimbal-200hz``), or a bias instability the model does not
have (``standard-inst``: ``residual_nulls.INSTABILITY``, first-order Gauss-Markov over 100 s).
Prints each session's findings (effect, sensor, regime, p). A right answer is no finding, or for
the instability an ``unknown`` (a bias instability is outside the catalogue), never a catalogue name.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from residual_nulls import PIPELINE, G, realistic_imu, tidy

from imupipe.pipeline.api import run_sessions
from imupipe.sim.api import simulate

VARIANTS = {  # protocol, protocol parameters, sensor: changes or "instability"
    "gimbal-rest2": ("gimbal", {"rest_s": 2.0}, {}),
    "gimbal-200hz": ("gimbal", {}, {"rate_hz": 200.0}),
    "standard-rest2": ("standard", {"rest_s": 2.0, "reference_rest_s": 4.0}, {}),
    "standard-inst": ("standard", {}, "instability"),
}


def one(args: tuple[str, int, str]) -> tuple[str, int, list | str]:
    name, seed, folder = args
    protocol, params, sensor = VARIANTS[name]
    imu = realistic_imu(seed, instability=sensor == "instability")
    if isinstance(sensor, dict):
        imu = imu.model_copy(update=sensor)
    path = Path(folder) / f"{name}-{seed}.mcap"
    simulate(protocol, {}, seed, path, quiet=True, params=params, imu=imu, env={"gravity_m_s2": G})
    out = Path(folder) / "out"
    try:
        run_sessions([path], PIPELINE[protocol], out, quiet=True, diagnose=True)
    except Exception as exc:  # noqa: BLE001 - a bench reports failures and goes on
        return name, seed, f"error: {exc}"
    doc = json.loads((out / path.stem / "diagnosis.json").read_text())
    tidy(path, out)
    return name, seed, [(f["effect"], f["sensor"], f["regime"], f["significance"]["p_value"]) for f in doc["findings"]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    folder = args.out or Path(tempfile.mkdtemp(prefix="diagnosis-variants-"))
    folder.mkdir(parents=True, exist_ok=True)
    jobs = [(name, seed, str(folder)) for name in args.variants for seed in range(args.seeds)]
    with ProcessPoolExecutor(args.jobs) as pool:
        for name, seed, findings in pool.map(one, jobs):
            print(f"{name:<16} seed {seed}: {findings or 'no finding'}", flush=True)


if __name__ == "__main__":
    main()

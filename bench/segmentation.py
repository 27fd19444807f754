"""Stillness segmentation against the simulator's true rests, from one run.

    python bench/segmentation.py [--seeds 3] [--set key=value ...] [--module OTHER/segment.py]

For each scenario (short holds of 2 s and 1.5 s, the gimbal's fast rotations, the
standard session, hand-held rests vibrating at 4-8 Hz) simulates sessions, runs the
``segment_stillness`` stage with its defaults (``--set`` overrides them) and prints:
the fraction of true rests found (a found rest whose middle lies in the true one),
the mean trim per end (true minus found, s, positive = inside the rest), the mean and
worst overreach into the motion (s), the fraction of found rests reaching more than 50 ms
into a motion, and found rests that match no true rest.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time

import numpy as np

from imupipe.sim.api import simulate_recording
from imupipe.sim.tremor import add_tremor
from imupipe.stages import segment

SCENARIOS = {
    "holds 2 s (one-stage rig)": ("sphere_rig_one_stage", dict(warmup_s=60, n_positions=60, rest_s=2.0), None),
    "holds 1.5 s (one-stage rig)": ("sphere_rig_one_stage", dict(warmup_s=60, n_positions=60, rest_s=1.5), None),
    "gimbal, holds 2 s": ("gimbal", dict(rest_s=2.0, n_rotations=20), None),
    "standard (5 s holds)": ("standard", dict(warmup_s=60, n_positions=40), None),
    "hand-held 4-8 Hz, holds 2 s": ("sphere_rig_one_stage", dict(warmup_s=60, n_positions=60, rest_s=2.0),
                                    dict(gyro_dps=1.0, accel_mg=5.0)),
    "hand-held 4-8 Hz, gimbal 2 s": ("gimbal", dict(rest_s=2.0, n_rotations=20), dict(gyro_dps=1.0, accel_mg=5.0)),
}


def score(found: np.ndarray, true: np.ndarray) -> dict:
    """found, true: (n, 2) s. Matching by the found rest's middle; true rests that touch
    (the warm-up and the first hold, with no motion between) count as one."""
    merged = [list(true[0])]
    for a, b in true[1:]:
        if a - merged[-1][1] < 1e-6:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    true = np.array(merged)
    hit, trims, over, false = np.zeros(len(true), bool), [], [], 0
    for a, b in found:
        j = np.flatnonzero((true[:, 0] <= 0.5 * (a + b)) & (0.5 * (a + b) <= true[:, 1]))
        if not len(j):
            false += 1
            continue
        ta, tb = true[j[0]]
        hit[j[0]] = True
        trims += [a - ta, tb - b]
        over += [max(0.0, ta - a), max(0.0, b - tb)]
    trims, over = np.array(trims), np.array(over)
    return {"found": hit.mean(), "n_true": len(true), "trim_s": trims.mean() if len(trims) else np.nan,
            "over_mean_s": over.mean() if len(over) else np.nan, "over_max_s": over.max() if len(over) else np.nan,
            "over_50ms": (over.reshape(-1, 2).max(axis=1) > 0.05).mean() if len(over) else np.nan,
            "false": false}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--set", nargs="*", default=[], help="segment params, key=value (JSON values)")
    ap.add_argument("--module", help="another segment.py to measure (e.g. main's: the before)")
    args = ap.parse_args()
    global segment
    if args.module:
        spec = importlib.util.spec_from_file_location("imupipe.stages.segment_other", args.module)
        segment = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(segment)
    params = segment.SegmentParams(**{k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)})
    print(f"segment_stillness version {segment.STAGE.version}, params {params.model_dump()}")
    print(f"{'scenario':32s} {'found':>7s} {'trim/end s':>10s} {'over mean':>9s} {'over max':>9s} "
          f"{'>50ms':>6s} {'false':>5s} {'s/run':>6s}")
    for name, (protocol, kw, vib) in SCENARIOS.items():
        rows = []
        for seed in range(args.seeds):
            rec, truth = simulate_recording(protocol, None, seed, **kw)
            d = dict(rec.device("imu"))
            if vib:
                d = add_tremor(d, np.random.default_rng([seed, 7]), **vib)
            t0 = time.perf_counter()
            try:
                r = segment.STAGE.func(d, params, None)["rests"]
                found = np.column_stack([r.column("t_start_s").to_numpy(), r.column("t_end_s").to_numpy()])
            except Exception as exc:  # noqa: BLE001 - a bench reports and goes on
                print(f"  seed {seed}: {type(exc).__name__}: {str(exc)[:200]}")
                found = np.zeros((0, 2))
            s = score(found, truth.rests)
            s["sec"] = time.perf_counter() - t0
            rows.append(s)
        m = {k: np.nanmean([r[k] for r in rows]) for k in rows[0]}
        worst = np.nanmax([r["over_max_s"] for r in rows])
        print(f"{name:32s} {m['found']:7.3f} {m['trim_s']:10.3f} {m['over_mean_s']:9.3f} {worst:9.3f} "
              f"{m['over_50ms']:6.3f} {m['false']:5.1f} {m['sec']:6.2f}")


if __name__ == "__main__":
    main()

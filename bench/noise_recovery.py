"""The noise stage against the simulator's truth on static recordings, from one run.

    python bench/noise_recovery.py [--seeds 4] [--duration 600]

Simulates powered-equilibrium static sessions (no thermal drift) with a bias random walk on
gyro (1e-5 rad/s^2/sqrt(Hz)) and accel (1e-4 m/s^3/sqrt(Hz)), runs segmentation and
``estimate_noise``, and prints per triad and axis the recovered noise density over the truth
(``sqrt(noise_sd^2 + LSB^2/12) / sqrt(rate)``: rounding is white) and random walk over the truth.
"""

from __future__ import annotations

import argparse

import numpy as np

from imupipe.sim.api import simulate_recording
from imupipe.stages import noise, segment

K = {"gyro": 1e-5, "accel": 1e-4}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--duration", type=float, default=600.0)
    args = ap.parse_args()
    effects = {"bias_random_walk": {"sigma": [K["gyro"]] * 3, "sensor": "gyro"},
               "bias_random_walk:accel": {"sigma": [K["accel"]] * 3, "sensor": "accel"}}
    ratios: dict[str, list] = {}
    for seed in range(args.seeds):
        rec, truth = simulate_recording("warmup", effects, seed, duration_s=args.duration, start_C=42.0)
        d = dict(rec.device("imu"))
        seg = segment.STAGE.func(d, segment.SegmentParams(), None)
        out = noise.STAGE.func({**d, "rests": seg["rests"]}, noise.NoiseParams(), None)
        imu = truth.data["imu"]
        for r in out["noise"].to_pylist():
            s = r["sensor"]
            n_true = np.sqrt(imu[s]["noise_sd"] ** 2 + imu[s]["quantum"] ** 2 / 12) / np.sqrt(imu["rate_hz"])
            ratios.setdefault(f"{s} N/N_true", []).append(r["noise_density"] / n_true)
            if s in K:
                ratios.setdefault(f"{s} K/K_true", []).append(r["random_walk"] / K[s])
    print(f"{args.seeds} seeds x 3 axes, {args.duration:.0f} s static at 100 Hz")
    for k, v in ratios.items():
        v = np.array(v)
        print(f"{k:18s} min {v.min():.3f}  median {np.median(v):.3f}  max {v.max():.3f}")


if __name__ == "__main__":
    main()

#!/usr/bin/env bash
# Regenerates examples/standard-session.mcap (+ .truth.json), the README's bundled example:
# a short standard session (warm-up, 80 positions joined by small turns, reference positions,
# roll turn, turntable) at 50 Hz, at a site whose gravity is standard gravity (9.80665 m/s^2),
# which is what the default pipeline assumes.
set -euo pipefail
cd "$(dirname "$0")"
imupipe simulate standard --seed 2026 --quiet \
  --param n_positions=80 --param warmup_s=120 \
  --imu rate_hz=50 --env gravity_m_s2=9.80665 \
  --out standard-session.mcap

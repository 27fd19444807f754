"""`imupipe run --pipeline ferraris` on imucal's example session, beside imucal's published numbers.

    python bench/peers_imucal_pipeline.py

Runs the shipped Ferraris pipeline from the command line on
``examples/sessions/imucal_ferraris.toml`` (imucal's section list, g = 9.81 as imucal sets it),
with and without imucal's gyro g-sensitivity term, and prints scale and bias beside imucal's,
then the first 50 calibrated rows beside imucal's own (``ferraris_example.csv``).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from imupipe import cli

REPO = Path(__file__).resolve().parents[1]
SESSION = REPO / "examples" / "sessions" / "imucal_ferraris.toml"
DATA = REPO.parent / "shared" / "data" / "imucal"
IMUCAL = {"accel_scale": [0.99675, 1.00244, 1.02340], "accel_bias": [0.537, -0.616, 0.399],
          "gyro_scale": [1.02792, 0.98243, 0.99831], "gyro_bias_dps": [-0.600, -0.370, 0.059]}


def main() -> None:
    raw = np.genfromtxt(DATA / "example_ferraris_session.csv", delimiter=",", names=True)[:50]
    ref = np.genfromtxt(DATA / "ferraris_example.csv", delimiter=",", names=True)
    for g_sens in (False, True):
        with tempfile.TemporaryDirectory() as out:
            args = ["run", str(SESSION), "--pipeline", "ferraris", "--out", out, "--quiet",
                    "--set", "ferraris.g_m_s2=9.81",
                    "--set", f"ferraris.solver_params.g_sensitivity={str(g_sens).lower()}"]
            assert cli.main(args) == 0
            doc = json.loads((Path(out) / "imucal_ferraris" / "calibration.json").read_text())
        acc, gyr = doc["accel"], doc["gyro"]
        print(f"imupipe ferraris pipeline, g_sensitivity = {g_sens}")
        print(f"  accel scale {np.round(acc['K'], 5)}   imucal {IMUCAL['accel_scale']}")
        print(f"  accel bias  {np.round(acc['b0'], 3)} +- {np.round(acc['sigma_b0'], 4)} m/s^2   "
              f"imucal {IMUCAL['accel_bias']}")
        print(f"  gyro scale  {np.round(gyr['K'], 5)}   imucal {IMUCAL['gyro_scale']}")
        print(f"  gyro bias   {np.round(np.degrees(gyr['b0']), 3)} +- "
              f"{np.round(np.degrees(gyr['sigma_b0']), 4)} deg/s   imucal {IMUCAL['gyro_bias_dps']}")
        for name, pre, unit in (("accel", "acc", 1.0), ("gyro", "gyr", np.pi / 180)):
            y = np.column_stack([raw[f"{pre}_{a}"] for a in "xyz"]) * unit
            t = doc[name]
            mine = (y - t["b0"]) @ np.array(t["M"]).T / unit
            theirs = np.column_stack([ref[f"{pre}_{a}"] for a in "xyz"])
            print(f"  first 50 rows, {name}: max |imupipe - imucal| {np.abs(mine - theirs).max():.2e}")
    print("(imucal's gyro correction also subtracts K_ga a; calibration.json's model has no such term)")


if __name__ == "__main__":
    main()

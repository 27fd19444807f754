"""`imupipe diagnose` on null sessions under variations another simulator may use.

    python bench/diagnosis_variants.py [--seeds 2] [--first-seed 0] [--variants NAME ...] [--jobs 2]

Each variant is a null (no omitted physics) of the benches' consumer-MEMS sensor
(``residual_nulls.realistic_imu``) with one thing changed: another protocol (``sphere-rig`` with the
default pipeline, ``ferraris`` with its own, whose segmentation is not given the temperature),
rests of 2 s (``gimbal-rest2``,
``standard-rest2``), a 200 Hz sensor (``gimbal-200hz``), or a bias instability the model does not
have (``standard-inst``: ``residual_nulls.INSTABILITY``, first-order Gauss-Markov over 100 s).
Seven more kinds change the recorded streams after the simulator, as real recordings differ from
it (the last field of ``VARIANTS``): hand-held rests vibrating at 4-8 Hz (``standard-tremor``, ``sim.tremor``), a knock
inside a turn (``standard-knock``: a 4 g, 20 ms jolt with a rattle of the gyro that comes back to
where it started), flicker noise, whose Allan deviation is flat where a walk's rises
(``gimbal-flicker``, ``standard-flicker``), and stamps jittered by a logger (``gimbal-jitter``,
``standard-jitter``: 0.5 ms sd, one stamp per message of all streams, order kept), white noise
shared by a triad's three axes (``gimbal-common``, ``standard-common``: as much again as each axis's
own, a correlation of 0.5), and single-sample glitches of a bus (``gimbal-glitch``,
``standard-glitch``: one every ``GLITCH_EVERY_S`` per triad, a quarter of its range on one axis),
and an accelerometer read at its own, lower rate (``gimbal-accel-rate``, ``standard-accel-rate``:
its samples at every ``ACCEL_STEP``-th index, about 73 Hz beside the gyro's 100 Hz).
Prints each session's findings (effect, sensor, regime, p) and how many sessions name a catalogue
effect. A right answer is no finding, or for what is outside the catalogue (the instability and
the seven kinds above) an ``unknown`` or a noise-model finding, never a catalogue name.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pyarrow as pa
from residual_nulls import INSTABILITY, PIPELINE, G, realistic_imu, session_out, tidy

from imupipe.components import Recording
from imupipe.pipeline.api import run_sessions
from imupipe.sim.api import simulate, simulate_recording
from imupipe.sim.tremor import add_tremor, with_added
from imupipe.writers.mcap import write_mcap

JITTER_S = 5e-4  # sd of a logger's stamping delay, s: the samples are uniform, their stamps are not
KNOCK = {"accel_g": 4.0, "accel_s": 0.02, "gyro_rad_s": 3.0, "gyro_s": 0.04}
COMMON_SD = {"accel": 0.5e-3 * G, "gyro": np.radians(0.02)}  # the benches' sensor's own white noise per sample
GLITCH_EVERY_S = 200.0
GLITCH = {"accel": 2.0 * G, "gyro": np.radians(125.0)}  # a quarter of its range: a high bit flipped
ACCEL_STEP = 1.37  # the accelerometer's sample spacing in gyro samples (another output data rate)


def tremor(streams: dict, truth, rng: np.random.Generator) -> dict:
    """Hand-held rests (``sim.tremor``, its defaults: 1 deg/s and 5 mg at 4-8 Hz)."""
    return add_tremor(streams, rng)


def knock(streams: dict, truth, rng: np.random.Generator) -> dict:
    """A knock in the middle of the turn nearest the session's middle: a half-sine jolt of the
    accelerometer and one period of a sine on the gyro (a rattle: no net turn)."""
    turns = truth.segments("turn")
    t = (streams["accel"].column("t_ns").to_numpy() - streams["accel"].column("t_ns")[0].as_py()) * 1e-9
    middle = [0.5 * (s["t_start_s"] + s["t_end_s"]) for s in turns]
    at = middle[int(np.argmin(np.abs(np.array(middle) - 0.5 * t[-1])))]
    out = dict(streams)
    for sensor, amp, width in (("accel", KNOCK["accel_g"] * G, KNOCK["accel_s"]),
                               ("gyro", KNOCK["gyro_rad_s"], KNOCK["gyro_s"])):
        u = rng.normal(size=3)
        phase = np.clip((t - at) / width, 0.0, 1.0)
        pulse = np.sin(np.pi * phase) if sensor == "accel" else np.sin(2 * np.pi * phase)
        out[sensor] = with_added(streams[sensor], amp * np.outer(pulse, u / np.linalg.norm(u)))
    return out


def jitter(streams: dict, truth, rng: np.random.Generator) -> dict:
    """Every stamp late by a random ``JITTER_S``-sd delay (the same for all streams of a sample,
    kept in order): the readings are where the sensor took them, their stamps are not."""
    t_ns = streams["accel"].column("t_ns").to_numpy()
    late = np.abs(rng.normal(0.0, JITTER_S * 1e9, len(t_ns))).astype(np.int64)
    stamped = np.maximum.accumulate(t_ns + late)
    stamped[1:] = np.maximum(stamped[1:], stamped[:-1] + 1)  # strictly increasing, as loggers write
    out = {}
    for name, table in streams.items():
        assert np.array_equal(table.column("t_ns").to_numpy(), t_ns), "the simulator stamps all streams alike"
        out[name] = table.set_column(table.column_names.index("t_ns"), "t_ns", pa.array(stamped))
    return out


def flicker(streams: dict, truth, rng: np.random.Generator) -> dict:
    """Flicker (1/f) noise on both triads, scaled to an Allan deviation of
    ``residual_nulls.INSTABILITY``'s sd at 10 s (its floor: flat, unlike a walk's)."""
    out = dict(streams)
    for sensor in ("accel", "gyro"):
        t_ns = streams[sensor].column("t_ns").to_numpy()
        n, dt = len(t_ns), float(np.median(np.diff(t_ns))) * 1e-9
        f = np.fft.rfftfreq(n, dt)
        shape = np.zeros_like(f)
        shape[1:] = f[1:] ** -0.5
        x = np.fft.irfft(np.fft.rfft(rng.normal(size=(3, n)), axis=1) * shape, n, axis=1).T
        m = round(10.0 / dt)
        means = x[: n // m * m].reshape(-1, m, 3).mean(axis=1)
        adev = np.sqrt(0.5 * np.mean(np.diff(means, axis=0) ** 2, axis=0))
        out[sensor] = with_added(streams[sensor], x * (INSTABILITY[sensor]["bias_gm_sd"] / adev))
    return out


def common(streams: dict, truth, rng: np.random.Generator) -> dict:
    """White noise the same on a triad's three axes (``COMMON_SD``): its axes' noise is correlated,
    as a shared reference or supply makes it."""
    out = dict(streams)
    for sensor, sd in COMMON_SD.items():
        n = streams[sensor].num_rows
        out[sensor] = with_added(streams[sensor], np.repeat(rng.normal(0.0, sd, (n, 1)), 3, axis=1))
    return out


def glitch(streams: dict, truth, rng: np.random.Generator) -> dict:
    """Single samples read wrong on one axis by ``GLITCH`` (either sign), one every
    ``GLITCH_EVERY_S`` on average per triad, as a bus's read errors do."""
    out = dict(streams)
    for sensor, size in GLITCH.items():
        t_ns = streams[sensor].column("t_ns").to_numpy()
        add = np.zeros((len(t_ns), 3))
        k = rng.poisson((t_ns[-1] - t_ns[0]) * 1e-9 / GLITCH_EVERY_S)
        add[rng.integers(0, len(t_ns), k), rng.integers(0, 3, k)] = size * rng.choice([-1.0, 1.0], k)
        out[sensor] = with_added(streams[sensor], add)
    return out


def accel_rate(streams: dict, truth, rng: np.random.Generator) -> dict:
    """The accelerometer at its own output data rate: its samples at every ``ACCEL_STEP``-th index,
    rounded down (their stamps, uneven against the gyro's, are where they were read)."""
    n = streams["accel"].num_rows
    return {**streams, "accel": streams["accel"].take(np.unique(np.arange(0, n, ACCEL_STEP).astype(int)))}


VARIANTS = {  # protocol, protocol parameters, sensor changes or "instability", what is done to its streams
    "gimbal-rest2": ("gimbal", {"rest_s": 2.0}, {}, None),
    "gimbal-200hz": ("gimbal", {}, {"rate_hz": 200.0}, None),
    "standard-rest2": ("standard", {"rest_s": 2.0, "reference_rest_s": 4.0}, {}, None),
    "standard-inst": ("standard", {}, "instability", None),
    "sphere-rig": ("sphere_rig", {}, {}, None),
    "ferraris": ("ferraris", {}, {}, None),
    "standard-tremor": ("standard", {}, {}, tremor),
    "standard-knock": ("standard", {}, {}, knock),
    **{f"{protocol}-{kind}": (protocol, {}, {}, after) for kind, after in (
        ("flicker", flicker), ("jitter", jitter), ("common", common), ("glitch", glitch), ("accel-rate", accel_rate))
       for protocol in ("gimbal", "standard")},
}


def one(args: tuple[str, int, str]) -> tuple[str, int, list | str]:
    name, seed, folder = args
    protocol, params, sensor, after = VARIANTS[name]
    imu = realistic_imu(seed, instability=sensor == "instability")
    if isinstance(sensor, dict):
        imu = imu.model_copy(update=sensor)
    path = Path(folder) / f"{name}-{seed}.mcap"
    if after:
        rec, truth = simulate_recording(protocol, {}, seed, imu=imu, env={"gravity_m_s2": G}, **params)
        streams = after(dict(rec.device()), truth, np.random.default_rng([seed, 11]))
        write_mcap(path, Recording(rec.source, {next(iter(rec.devices)): streams}))
    else:
        simulate(protocol, {}, seed, path, quiet=True, params=params, imu=imu, env={"gravity_m_s2": G})
    out = session_out(folder, path)
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
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    folder = args.out or Path(tempfile.mkdtemp(prefix="diagnosis-variants-"))
    folder.mkdir(parents=True, exist_ok=True)
    jobs = [(name, seed, str(folder)) for name in args.variants for seed in range(args.first_seed, args.first_seed + args.seeds)]
    named = 0
    with ProcessPoolExecutor(args.jobs) as pool:
        for name, seed, findings in pool.map(one, jobs):
            print(f"{name:<16} seed {seed}: {findings or 'no finding'}", flush=True)
            named += isinstance(findings, str) or any(f[0] != "unknown" for f in findings)
    print(f"sessions naming a catalogue effect (or failing): {named}/{len(jobs)} (right: 0)")


if __name__ == "__main__":
    main()

"""Ingest benchmark: imupipe's MCAP reader against the mcap_ros2 decoder and raw zstd.

Writes a ROS 2 MCAP of >= 1,000,000 messages (one IMU: Imu at 1 kHz,
MagneticField at 100 Hz, Temperature at 10 Hz, interleaved by time, zstd
chunks of 1 MiB) into a temporary directory, then prints, from this one run:

* imupipe's ingest rate (``ingest.read_recording``: reader + stream checks),
  wall clock and CPU time (all threads: the reader decompresses ahead in a thread),
* the mcap_ros2 reference decoder's rate (timed on the first messages of the
  same file only and extrapolated; the output says how many),
* the raw zstd decompression rate of the same chunks (messages/s and MB/s),
* the ratios (targets: >= 100x the reference, >= 40 % of decompression),
* ``imupipe ingest FILE`` as a whole process, as a user runs it (interpreter start,
  imports, the plugin registry, reading, writing the tables; best of 3): wall and CPU,
  and the same ratios end to end, beside their floor: a process that only starts Python
  and imports numpy and pyarrow, plus the in-process read,
* peak memory of one ingest (peak resident size minus the size before, in a
  fresh process, and the tracemalloc peak) against the size of the decoded
  arrays (target <= 3x).

Wall-clock ratios suffer when other processes share the cores; the CPU-time
ratios are the steadier comparison of work done.

Usage: ``python bench/ingest.py [--seconds 910] [--reference-messages 30000]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import zstandard

from imupipe.components import Recording
from imupipe.writers.mcap import write_mcap

RATES_HZ = {"imu": 1000, "mag": 100, "temperature": 10}

# Runs in a fresh interpreter so that the peak resident size measures one ingest.
MEMORY_PROBE = """
import json, sys, tracemalloc
import imupipe.readers
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry

def status_bytes(key):  # VmRSS: resident now; VmHWM: peak resident of this process image
    # (not ru_maxrss: Linux carries that over from the parent across fork + exec)
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(key))

registry = make_registry([imupipe.readers], entry_points_too=False)
before = status_bytes("VmRSS:")
rec = read_recording(sys.argv[1], registry)
after = status_bytes("VmHWM:")
arrays = sum(t.nbytes for s in rec.devices.values() for t in s.values())
del rec
tracemalloc.start()
rec = read_recording(sys.argv[1], registry)
peak = tracemalloc.get_traced_memory()[1]
print(json.dumps({"rss_delta": after - before, "tracemalloc_peak": peak, "arrays": arrays}))
"""


def make_recording(seconds: float, seed: int = 0) -> Recording:
    """One IMU at rest with noise: accel m/s^2, gyro rad/s, mag T, temperature degC."""
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000_000_000_000

    def stamps(rate):
        return t0 + np.arange(int(seconds * rate), dtype=np.int64) * (1_000_000_000 // rate)

    def triad(t, mean, sd):
        return pa.table({"t_ns": t, **{c: m + sd * rng.standard_normal(len(t))
                                       for c, m in zip("xyz", mean)}})

    t_imu, t_mag, t_temp = (stamps(RATES_HZ[k]) for k in ("imu", "mag", "temperature"))
    streams = {
        "accel": triad(t_imu, (0.0, 0.0, 9.81), 0.02),
        "gyro": triad(t_imu, (0.0, 0.0, 0.0), 0.001),
        "mag": triad(t_mag, (2e-5, 0.0, -4e-5), 1e-7),
        "temperature": pa.table({"t_ns": t_temp,
                                 "temperature": 30.0 + 0.01 * rng.standard_normal(len(t_temp))}),
    }
    return Recording(source="bench", devices={"imu": streams})


def best_of(fn, repeats: int = 3) -> tuple[float, float, object]:
    """Lowest wall-clock and lowest CPU seconds (all threads) of ``fn()`` over ``repeats`` runs."""
    wall = cpu = float("inf")
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        result = fn()
        wall, cpu = min(wall, time.perf_counter() - w), min(cpu, time.process_time() - c)
    return wall, cpu, result


def time_imupipe(path: Path) -> tuple[float, float, int]:
    import imupipe.readers
    from imupipe.ingest import read_recording
    from imupipe.plugins import make_registry

    registry = make_registry([imupipe.readers], entry_points_too=False)  # the readers only
    wall, cpu, rec = best_of(lambda: read_recording(path, registry), repeats=5)
    return wall, cpu, sum(t.num_rows for s in rec.devices.values() for t in s.values())


def time_reference(path: Path, limit: int) -> tuple[float, float, int]:
    """Seconds to decode the first ``limit`` messages with mcap_ros2, and how many it decoded."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    def decode() -> int:
        count = 0
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            # log-time order (the file's order here) decodes lazily, chunk by chunk; with
            # log_time_order=False mcap splits every chunk of the file before the first message
            for _ in reader.iter_decoded_messages():
                count += 1
                if count >= limit:
                    break
        return count

    return best_of(decode, repeats=1)


def time_decompression(path: Path) -> tuple[float, float, int]:
    """Seconds to zstd-decompress every chunk (data already in memory), uncompressed bytes."""
    from mcap.reader import SeekingReader

    with open(path, "rb") as f:
        summary = SeekingReader(f).get_summary()
        blobs = []
        for index in summary.chunk_indexes:
            f.seek(index.chunk_start_offset + 1 + 8 + 8 + 8 + 8 + 4)
            clen = int.from_bytes(f.read(4), "little")
            f.seek(clen + 8, 1)
            blobs.append((f.read(index.compressed_size), index.uncompressed_size))
    dctx = zstandard.ZstdDecompressor()
    return best_of(lambda: sum(len(dctx.decompress(b, max_output_size=n)) for b, n in blobs),
                   repeats=5)


def time_process(cmd: list[str], repeats: int = 3) -> tuple[float, float]:
    """Best wall and CPU seconds of ``cmd`` (a child process)."""
    import os

    wall = cpu = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
        _, status, usage = os.wait4(proc.pid, 0)
        if os.waitstatus_to_exitcode(status):
            sys.exit(f"{' '.join(cmd)} failed")
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, usage.ru_utime + usage.ru_stime)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=910.0,
                    help="recording length (910 s: 1.01 M messages)")
    ap.add_argument("--reference-messages", type=int, default=30_000)
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="imupipe-bench-") as tmp:
        path = Path(tmp) / "bench.mcap"
        recording = make_recording(args.seconds)
        n_msgs = sum(int(args.seconds * r) for r in RATES_HZ.values())
        start = time.perf_counter()
        write_mcap(path, recording)
        write_s = time.perf_counter() - start
        del recording
        size_mb = path.stat().st_size / 1e6
        print(f"file: {n_msgs:,} messages (Imu {RATES_HZ['imu']} Hz, MagneticField "
              f"{RATES_HZ['mag']} Hz, Temperature {RATES_HZ['temperature']} Hz), {size_mb:.1f} MB "
              f"zstd, written in {write_s:.1f} s")

        ours_s, ours_cpu, rows = time_imupipe(path)
        ref_s, ref_cpu, ref_n = time_reference(path, args.reference_messages)
        dec_s, dec_cpu, dec_bytes = time_decompression(path)
        ours, ref, dec = n_msgs / ours_s, ref_n / ref_s, n_msgs / dec_s
        print(f"imupipe ingest (read_recording: reader + stream checks, best of 5): {ours_s:.3f} s "
              f"-> {ours:,.0f} msg/s ({rows:,} table rows; CPU {ours_cpu:.3f} s)")
        print(f"mcap_ros2 reference decoder: {ref_n:,} messages in {ref_s:.3f} s -> "
              f"{ref:,.0f} msg/s (timed on the first {ref_n:,} messages only, extrapolated: "
              f"{n_msgs / ref:.0f} s for all; CPU {ref_cpu:.3f} s)")
        print(f"raw zstd decompression of the same chunks (best of 5): {dec_s:.3f} s -> "
              f"{dec:,.0f} msg/s equivalent, {dec_bytes / dec_s / 1e6:,.0f} MB/s "
              f"({dec_bytes / 1e6:.0f} MB uncompressed; CPU {dec_cpu:.3f} s)")
        per_cpu = (n_msgs / ours_cpu) / (ref_n / ref_cpu), dec_cpu / ours_cpu
        print(f"ratio imupipe / reference:     {ours / ref:8.1f}x  wall, {per_cpu[0]:8.1f}x  CPU "
              f"(target >= 100x)")
        print(f"ratio imupipe / decompression: {ours / dec:8.1%}   wall, {per_cpu[1]:8.1%}   CPU "
              f"(target >= 40 %)")

        whole_s, whole_cpu = time_process([sys.executable, "-m", "imupipe", "ingest", str(path),
                                           "--out", str(Path(tmp) / "tables")])
        print(f"imupipe ingest as a whole process (python -m imupipe ingest, best of 3): "
              f"{whole_s:.3f} s wall, {whole_cpu:.3f} s CPU; end to end "
              f"{(n_msgs / whole_s) / ref:.1f}x the reference (wall), "
              f"{(n_msgs / whole_cpu) / (ref_n / ref_cpu):.1f}x (CPU) (target >= 100x); "
              f"{dec_s / whole_s:.1%} of decompression (wall), {dec_cpu / whole_cpu:.1%} (CPU) "
              "(target >= 40 %)")
        floor_s, floor_cpu = time_process([sys.executable, "-c", "import numpy, pyarrow"])
        print(f"the floor of a whole process: starting Python and importing numpy and pyarrow takes "
              f"{floor_s:.3f} s wall ({floor_cpu:.3f} s CPU); with the read above, "
              f"{floor_s + ours_s:.3f} s: at most {(n_msgs / (floor_s + ours_s)) / ref:.1f}x the "
              f"reference and {dec_s / (floor_s + ours_s):.1%} of decompression end to end (wall), "
              "before the registry or a table written")

        probe = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(path)],
                               capture_output=True, text=True, check=True)
        mem = json.loads(probe.stdout)
        arrays = mem["arrays"]
        rss = mem["rss_delta"]
        print(f"decoded arrays: {arrays / 1e6:.1f} MB; peak during one ingest (fresh process): "
              f"peak RSS - RSS before {rss / 1e6:.1f} MB = {rss / arrays:.2f}x, "
              f"tracemalloc peak {mem['tracemalloc_peak'] / 1e6:.1f} MB = "
              f"{mem['tracemalloc_peak'] / arrays:.2f}x   (target <= 3x)")


if __name__ == "__main__":
    main()

"""Issue 12: ``imupipe run`` killed with SIGKILL mid-run leaves nothing that looks complete,
and the next run succeeds (the contract: ``calibration.json`` appears only with the full set
of outputs; cache entries are complete or absent; stale ``.part`` files are removed)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from imupipe.pipeline.cache import Cache
from imupipe.pipeline.config import default_pipeline_path
from imupipe.sim.api import simulate_recording, write_csv

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL is POSIX")


def _light_pipeline(folder: Path) -> Path:
    """The default pipeline without its residual map and reports (the kill lands in its stages)."""
    text = default_pipeline_path().read_text()
    head, _, rest = text.partition("[stages.map]")
    export = "\n".join(line for line in rest[rest.index("[export]"):].splitlines()
                       if not line.startswith("reports"))
    path = folder / "light.toml"
    path.write_text(head + export + "\n")
    return path


def _run(session: Path, pipeline: Path, out: Path) -> subprocess.Popen:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "imupipe.cli", "run", str(session), "--out", str(out),
                             "--pipeline", str(pipeline), "--quiet"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)


def _entries(out: Path) -> list[Path]:
    return sorted((out / ".cache").glob("*/*/outputs.json"))


def test_sigkill_mid_run_leaves_nothing_that_looks_complete_and_the_rerun_succeeds(tmp_path):
    recording, _ = simulate_recording("sphere_rig", seed=3, imu={"rate_hz": 25}, warmup_s=5,
                                      n_positions=12, n_turns=8, rest_s=2, reference_rest_s=2)
    session = tmp_path / "s.csv"
    write_csv(session, recording)
    pipeline = _light_pipeline(tmp_path)
    out = tmp_path / "out"
    proc = _run(session, pipeline, out)
    deadline = time.monotonic() + 60
    while len(_entries(out)) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)  # kill between stages: two cache entries written, more to come
    assert proc.poll() is None, "the run ended before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    # nothing looks complete: no calibration, every cache entry verifies, every JSON parses
    assert not list(out.rglob("calibration.json"))
    cache = Cache(out / ".cache")
    assert _entries(out) and all(cache.entry(p.parent.name) is not None for p in _entries(out))
    for p in out.rglob("*.json"):
        json.loads(p.read_text())
    # the rerun succeeds from the verified entries and leaves no staging or .part behind
    rerun = _run(session, pipeline, out)
    stdout, stderr = rerun.communicate(timeout=120)
    assert rerun.returncode == 0, stderr.decode()
    doc = json.loads((out / "s" / "calibration.json").read_text())
    assert doc["verdict"]["status"] in ("pass", "warn") and "accel" in doc and "gyro" in doc
    assert not [p for p in out.rglob("*") if ".part" in p.name]

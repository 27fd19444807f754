"""Checks every format shares: a recording must hold IMU data; one line and exit 2 when not."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from imupipe import schemas
from imupipe.cli import main
from imupipe.components import Recording
from imupipe.writers.mcap import write_mcap


def test_temperature_only_recording_is_rejected(tmp_path, capsys):
    t_ns = np.arange(1, 11, dtype=np.int64) * 10_000_000
    temperature = schemas.stamp(pa.table({"t_ns": t_ns, "temperature": np.full(10, 25.0)}), "temperature")
    path = tmp_path / "temperature_only.mcap"
    write_mcap(path, Recording(source="test", devices={"imu": {"temperature": temperature}}))
    out = tmp_path / "out"
    assert main(["ingest", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert str(path) in err and "holds no IMU data" in err and "found: temperature" in err
    assert not out.exists()


def test_quiet_is_accepted_by_every_command(tmp_path, capsys):
    assert main(["plugins", "--quiet"]) == 0
    assert main(["status", "--out", str(tmp_path), "--quiet"]) == 0

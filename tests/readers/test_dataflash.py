"""ArduPilot DataFlash ``.bin``: several IMUs kept apart, units, frames, bad logs.

The log is written byte by byte by ``tests/dataflash_synth.py`` from the documented
format (FMT-defined messages, ArduPilot 4.x ``IMU``/``MAG`` layouts) and read
back through pymavlink's ``DFReader``.
"""

from __future__ import annotations

import numpy as np
import pytest
from dataflash_synth import write_dataflash

import imupipe.readers
from imupipe import cli
from imupipe.errors import ReaderError
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry

pytest.importorskip("pymavlink", reason="needs the ardupilot extra (pymavlink)")


@pytest.fixture
def registry():
    return make_registry([imupipe.readers], entry_points_too=False)


def col(table, names):
    return np.column_stack([table.column(c).to_numpy() for c in names])


def test_imus_are_kept_apart_in_si(tmp_path, registry):
    path = tmp_path / "flight.bin"
    truth = write_dataflash(path, n=120, imus=3)
    rec = read_recording(path, registry)
    assert sorted(rec.devices) == ["imu0", "imu1", "imu2", "mag0"]
    for i in range(3):
        t_us, acc, gyro, temp = truth[f"imu{i}"]
        dev = rec.devices[f"imu{i}"]
        assert sorted(dev) == ["accel", "gyro", "temperature"]
        np.testing.assert_array_equal(dev["accel"].column("t_ns").to_numpy(),
                                      t_us.astype(np.int64) * 1000)
        np.testing.assert_array_equal(col(dev["accel"], "xyz"), acc.astype(np.float64))
        np.testing.assert_array_equal(col(dev["gyro"], "xyz"), gyro.astype(np.float64))
        np.testing.assert_array_equal(dev["temperature"].column("temperature").to_numpy(),
                                      temp.astype(np.float64))
        assert dev["accel"].schema.metadata[b"imupipe.frame_convention"] == b"FRD"
    t_us, mag = truth["mag0"]
    np.testing.assert_allclose(col(rec.devices["mag0"]["mag"], "xyz"), mag * 1e-7, rtol=1e-15)


def test_logged_calibration_is_reported(tmp_path, registry):
    path = tmp_path / "cal.bin"
    write_dataflash(path, params={"INS_ACCOFFS_X": 0.25, "INS_ACCSCAL_X": 1.0,
                                  "COMPASS_DIA_X": 1.0, "LOG_BITMASK": 7.0})
    with pytest.warns(UserWarning, match=r"already corrected by INS_ACCOFFS_X; a calibration"):
        rec = read_recording(path, registry)
    assert rec.meta["parameters"] == {"INS_ACCOFFS_X": 0.25, "INS_ACCSCAL_X": 1.0,
                                      "COMPASS_DIA_X": 1.0}


def test_cut_off_log_keeps_its_complete_messages(tmp_path, registry):
    path = tmp_path / "cut.bin"
    write_dataflash(path, n=50, imus=1)
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.warns(UserWarning, match="are no complete message"):
        rec = read_recording(path, registry)
    assert rec.devices["imu0"]["accel"].num_rows == 49


def test_log_without_imu_messages(tmp_path, registry, capsys):
    path = tmp_path / "params.bin"
    write_dataflash(path, n=0, imus=0, params={"LOG_BITMASK": 0.0})
    with pytest.raises(ReaderError, match="params.bin: no IMU or MAG messages"):
        read_recording(path, registry)
    assert cli.main(["ingest", str(path), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_not_a_dataflash_log(tmp_path, registry):
    path = tmp_path / "firmware.bin"
    path.write_bytes(b"\x7fELF" + bytes(100))
    with pytest.raises(ReaderError, match="no reader accepts this file"):
        read_recording(path, registry)

"""PX4 ULog: sensor_combined and per-instance topics of pyulog's own test logs."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import imupipe.readers
from imupipe.errors import ReaderError
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry
from imupipe.readers.ulog import UlogReader

pyulog = pytest.importorskip("pyulog", reason="needs the px4 extra (pyulog)")


@pytest.fixture
def samples(shared_data):
    return shared_data / "pyulog_samples"


@pytest.fixture
def registry():
    return make_registry([imupipe.readers], entry_points_too=False)


def test_sensor_combined(samples, registry):
    path = samples / "sample.ulg"
    rec = read_recording(path, registry)  # also runs the shared ordering/NaN checks
    dev = rec.device()
    assert sorted(dev) == ["accel", "gyro", "mag"]
    raw = pyulog.ULog(str(path), ["sensor_combined"]).data_list[0].data
    assert dev["accel"].num_rows == len(raw["timestamp"]) == 17070
    np.testing.assert_array_equal(dev["gyro"].column("t_ns").to_numpy(),
                                  raw["timestamp"].astype(np.int64) * 1000)
    np.testing.assert_array_equal(dev["accel"].column("z").to_numpy(),
                                  raw["accelerometer_m_s2[2]"].astype(np.float64))
    # the topic repeats the latest mag sample: each distinct one is kept once, in tesla
    t_mag = raw["timestamp"].astype(np.int64) + raw["magnetometer_timestamp_relative"]
    assert dev["mag"].num_rows == np.unique(t_mag).size == 6759
    norm = np.linalg.norm([dev["mag"].column(a).to_numpy() for a in "xyz"], axis=0)
    assert 1e-5 < np.median(norm) < 1e-4  # Earth's field, 10..100 uT


def test_instances_become_devices_with_temperature(samples, registry):
    rec = read_recording(samples / "sample_log_small.ulg", registry)
    assert sorted(rec.devices) == ["imu", "imu0", "imu1", "imu2", "mag0", "mag1"]
    for i in range(3):
        assert sorted(rec.devices[f"imu{i}"]) == ["accel", "gyro", "temperature"]
    temp = rec.devices["imu0"]["temperature"].column("temperature").to_numpy()
    assert temp[0] == pytest.approx(40.02537, abs=1e-5)
    assert rec.devices["imu0"]["accel"].column("t_ns")[0].as_py() == 21_311_647_000
    with pytest.raises(ReaderError, match="holds 6 IMUs"):
        rec.device()


def test_not_a_ulog(tmp_path):
    path = tmp_path / "bad.ulg"
    path.write_bytes(b"ULog\x01\x12\x35garbage")
    assert UlogReader().sniff(path, path.read_bytes())
    with pytest.raises(ReaderError, match="not a readable ULog file"):
        UlogReader().read(path)


def test_missing_pyulog_names_the_extra(samples, monkeypatch):
    from imupipe.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, "pyulog", None)  # import now fails
    with pytest.raises(MissingExtraError, match=r"imupipe\[px4\]"):
        UlogReader().read(samples / "sample.ulg")


def _rows(rec) -> int:
    return rec.devices["imu"]["accel"].num_rows


def test_intact_log_reads_without_a_warning(samples, registry, recwarn):
    read_recording(samples / "sample_log_small.ulg", registry)
    assert not [w for w in recwarn if "ulg" in str(w.message)]


def test_truncated_log_warns_that_samples_are_missing(samples, registry, tmp_path):
    raw = (samples / "sample_log_small.ulg").read_bytes()
    path = tmp_path / "cut.ulg"
    path.write_bytes(raw[: int(len(raw) * 0.6)])  # mid-message, as a lost power or copy leaves it
    with pytest.warns(UserWarning, match=r"cut\.ulg: it ends mid-message at byte \d+ of 552978 "
                                         r"\(truncated: the samples recorded after it are missing"):
        rec = read_recording(path, registry)
    assert _rows(rec) < _rows(read_recording(samples / "sample_log_small.ulg", registry))


def test_zeroed_region_warns_with_its_size_and_place(samples, registry, tmp_path):
    raw = bytearray((samples / "sample_log_small.ulg").read_bytes())
    a, b = int(len(raw) * 0.4), int(len(raw) * 0.5)
    raw[a:b] = bytes(b - a)
    path = tmp_path / "zeroed.ulg"
    path.write_bytes(bytes(raw))
    with pytest.warns(UserWarning, match=r"zeroed\.ulg: \d+ bytes \(10 % of the log\) are zeroed or "
                                         r"damaged \(1 region, the first at bytes 368\d+-46\d+\): the "
                                         r"samples in them are missing") as rec_w:
        rec = read_recording(path, registry)
    assert len([w for w in rec_w if "zeroed" in str(w.message)]) == 1
    assert _rows(rec) < _rows(read_recording(samples / "sample_log_small.ulg", registry))


def test_zeroed_region_is_found_in_a_log_without_sync_messages(samples, tmp_path):
    from imupipe.readers.ulog import unreadable

    raw = bytearray((samples / "sample.ulg").read_bytes())  # an older log: no sync messages
    raw[1_000_000:1_050_000] = bytes(50_000)
    bad, cut = unreadable(bytes(raw))
    assert cut == 0 and len(bad) == 1
    start, end = bad[0]
    assert abs(start - 1_000_000) < 300 and 1_050_000 <= end < 1_050_000 + 300  # message bounds

"""MATLAB v7.3 (HDF5) buffers: sunsided/sensor-fusion files, alone and through a manifest."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

import imupipe.readers
from imupipe.errors import ReaderError
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry
from imupipe.readers.manifest import G0
from imupipe.readers.matlab import MatlabReader, read_buffer

h5py = pytest.importorskip("h5py", reason="needs the matlab extra (h5py)")


@pytest.fixture
def full_sphere(shared_data):
    return shared_data / "sunsided_mpu6050_hmc5883l" / "data" / "set-2" / "full-sphere"


@pytest.fixture
def registry():
    return make_registry([imupipe.readers], entry_points_too=False)


def test_buffers_are_transposed_to_samples_by_columns(full_sphere):
    buf = read_buffer(full_sphere / "mpu6050_accelerometer.mat")
    assert buf.shape == (10528, 4)
    # golden: the first sample as h5py shows it (rows t, x, y, z of the HDF5 dataset)
    assert buf[0, 0] == pytest.approx(0.00846300555, rel=1e-9)  # host time, s
    assert list(buf[0, 1:]) == [0.052001953125, -0.1826171875, -1.0107421875]  # g, exact
    assert (np.diff(buf[:, 0]) > 0).all()
    assert read_buffer(full_sphere / "mpu6050_temperature.mat").shape == (10528, 2)


def test_a_file_alone_is_read_with_sunsided_units(full_sphere, registry):
    for name, stream, factor in [("mpu6050_accelerometer.mat", "accel", G0),
                                 ("mpu6050_gyroscope.mat", "gyro", math.pi / 180),
                                 ("hmc5883l_compass.mat", "mag", 1e-4)]:
        path = full_sphere / name
        rec = read_recording(path, registry)
        table = rec.device()[stream]
        raw = read_buffer(path)
        np.testing.assert_allclose(table.column("x").to_numpy(), raw[:, 1] * factor, rtol=1e-15)
        assert table.column("t_ns").to_numpy()[0] == round(raw[0, 0] * 1e9)


def test_sniff_is_the_matlab_73_header(full_sphere, tmp_path):
    path = full_sphere / "mpu6050_gyroscope.mat"
    head = path.read_bytes()[:64]
    assert MatlabReader().sniff(path, head)
    text = tmp_path / "xsens_acc.mat"
    text.write_text("1 2 3 4\n")
    assert not MatlabReader().sniff(text, text.read_bytes())


def test_unknown_variables_and_bad_files_are_named(tmp_path):
    path = tmp_path / "other.mat"
    with h5py.File(path, "w") as f:
        f["something"] = np.zeros((4, 3))
        f["more"] = np.zeros((2, 3))
    with pytest.raises(ReaderError, match="no known buffer"):
        MatlabReader().read(path)
    with pytest.raises(ReaderError, match="holds variables more, something"):
        read_buffer(path)
    with pytest.raises(ReaderError, match="no variable 'x'"):
        read_buffer(path, "x")
    fake = tmp_path / "fake.mat"
    fake.write_bytes(b"MATLAB 5.0 MAT-file" + b"\0" * 200)
    with pytest.raises(ReaderError, match="not a MATLAB v7.3"):
        read_buffer(fake)


def test_manifest_variable_and_column_choice(tmp_path, registry):
    path = tmp_path / "log.mat"
    data = np.array([[0.0, 0.1, 0.2], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
    with h5py.File(path, "w") as f:
        f["magData"] = data  # MATLAB layout: (k, n) in HDF5
    manifest = tmp_path / "session.toml"
    manifest.write_text("""
[session]
name = "m"
[[streams]]
stream = "mag"
file = "log.mat"
variable = "magData"
columns = { t = 0, x = 3, y = 2, z = 1 }
unit = "uT"
""")
    mag = read_recording(manifest, registry).device()["mag"]
    assert mag.column("t_ns").to_pylist() == [0, 100_000_000, 200_000_000]
    assert mag.column("x").to_pylist() == pytest.approx([7e-6, 8e-6, 9e-6])
    assert mag.column("z").to_pylist() == pytest.approx([1e-6, 2e-6, 3e-6])


def test_missing_h5py_names_the_extra(full_sphere, monkeypatch):
    from imupipe.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, "h5py", None)  # import now fails
    with pytest.raises(MissingExtraError, match=r"imupipe\[matlab\]"):
        MatlabReader().read(full_sphere / "mpu6050_gyroscope.mat")


def test_a_corrupt_data_block_is_named(tmp_path):
    path = tmp_path / "hbad.mat"
    buf = np.column_stack([np.arange(3000) * 0.01, 9.81 + np.zeros((3000, 3))]).T
    with h5py.File(path, "w", userblock_size=512) as f:
        f.create_dataset("acc", data=buf, compression="gzip", chunks=(4, 500))
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 400] = bytes(b ^ 0xA5 for b in data[middle:middle + 400])
    path.write_bytes(bytes(data))
    with pytest.raises(ReaderError, match=r"hbad.mat: variable 'acc' cannot be read .* damaged"):
        read_buffer(path, "acc")

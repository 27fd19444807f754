"""The example plugin: discovered through its entry point, reads imu_tk's ASCII files."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import imupipe.readers
import numpy as np
import pytest
from imupipe.cli import main
from imupipe.errors import ReaderError
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry

imupipe_imutk = pytest.importorskip(
    "imupipe_imutk", reason="plugin not installed: pip install -e plugins/imupipe-imutk")
from imupipe_imutk.reader import ImutkTextReader

XSENS = Path(__file__).resolve().parents[4] / "shared" / "data" / "imu_tk_xsens"


def installed() -> bool:
    try:
        version("imupipe-imutk")
    except PackageNotFoundError:
        return False
    return True


@pytest.fixture
def xsens_slice(tmp_path) -> Path:
    """The first 300 lines of imu_tk's xsens_acc.mat (a real slice; the file is 3 MB)."""
    src = XSENS / "xsens_acc.mat"
    if not src.is_file():
        pytest.skip(f"no shared data at {src}")
    path = tmp_path / "xsens_acc.mat"
    with open(src) as f:
        path.write_text("".join(next(f) for _ in range(300)))
    return path


@pytest.mark.skipif(not installed(), reason="imupipe-imutk is not installed as a distribution")
def test_entry_point_discovery_names_distribution_and_version(capsys):
    registry = make_registry()
    component = registry.components["readers"]["imutk_text"]
    assert (component.plugin, component.distribution, component.dist_version) == (
        "imutk", "imupipe-imutk", imupipe_imutk.__version__)
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert f"imutk  (imupipe-imutk {imupipe_imutk.__version__})" in out
    assert "reader:imutk_text" in out


def test_reads_a_real_xsens_slice(xsens_slice):
    registry = make_registry([imupipe_imutk, imupipe.readers], entry_points_too=False)
    rec = read_recording(xsens_slice, registry)
    table = rec.device()["accel"]
    assert table.num_rows == 300
    # golden: first line "2.9840000e-02 3.3108000e+04 3.3329000e+04 3.6429000e+04"
    assert table.column("t_ns")[0].as_py() == 29_840_000
    assert [table.column(a)[0].as_py() for a in "xyz"] == [33108.0, 33329.0, 36429.0]
    assert table.schema.metadata[b"imupipe.source_unit"] == b"counts"
    assert (np.diff(table.column("t_ns").to_numpy()) > 0).all()


def test_sniff_leaves_other_formats_alone(tmp_path):
    reader = ImutkTextReader()
    mat = tmp_path / "real.mat"
    mat.write_bytes(b"MATLAB 7.3 MAT-file, Platform: x" + b"\0" * 40)
    csv = tmp_path / "a.csv"
    csv.write_text("t_ns,accel_x,accel_y,accel_z\n0,1,2,3\n")
    three = tmp_path / "gyro.txt"
    three.write_text("1 2 3\n")
    text = tmp_path / "gyro.txt2"
    text.write_text("1 2 3 4\n")
    for path in (mat, csv, three, text):
        assert not reader.sniff(path, path.read_bytes()[:64]), path


def test_bad_files_name_the_line(tmp_path):
    reader = ImutkTextReader()
    path = tmp_path / "imu_gyro.txt"
    path.write_text("0.01 1 2 3\n0.02 1 x 3\n")
    with pytest.raises(ReaderError, match="line 2: not a number"):
        reader.read(path)
    path.write_text("0.01 1 2 3\n0.02 1 2\n")
    with pytest.raises(ReaderError, match="line 2: 3 columns, expected 4"):
        reader.read(path)
    nameless = tmp_path / "data.txt"
    nameless.write_text("0.01 1 2 3\n")
    with pytest.raises(ReaderError, match="cannot tell the sensor from the file name"):
        reader.read(nameless)


@pytest.mark.skipif(not installed(), reason="imupipe-imutk is not installed as a distribution")
def test_a_manifest_can_name_the_plugin_reader(xsens_slice, tmp_path):
    gyro = tmp_path / "xsens_gyro.mat"
    gyro.write_text(xsens_slice.read_text())
    manifest = tmp_path / "session.toml"
    manifest.write_text("""
[session]
name = "imutk"
[[streams]]
stream = "accel"
file = "xsens_acc.mat"
reader = "imutk_text"
[[streams]]
stream = "gyro"
file = "xsens_gyro.mat"
reader = "imutk_text"
unit = "counts"
""")
    rec = read_recording(manifest, make_registry())
    assert sorted(rec.device()) == ["accel", "gyro"]
    assert rec.device()["gyro"].column("x")[0].as_py() == 33108.0

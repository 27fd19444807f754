"""Session manifests: the shipped examples on the real data, units, time bases, errors."""

from __future__ import annotations

import csv
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

import imupipe.readers
from imupipe.cli import main
from imupipe.errors import ConfigError, ReaderError
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry
from imupipe.readers.manifest import G0, ManifestReader

REPO = Path(__file__).resolve().parents[2]
SESSIONS = REPO / "examples" / "sessions"
DATA = REPO.parent / "shared" / "data"
DEG = math.pi / 180


@pytest.fixture
def registry():
    return make_registry([imupipe.readers], entry_points_too=False)


def first_rows(path: Path, n: int, skip: int = 0) -> list[dict[str, str]]:
    """The first rows of a CSV read independently of imupipe (Python's csv module)."""
    with open(path, newline="") as f:
        for _ in range(skip):
            next(f)
        reader = csv.DictReader(f)
        return [next(reader) for _ in range(n)]


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- shipped examples


def test_imucal_ferraris_golden(shared_data, registry):
    rec = read_recording(SESSIONS / "imucal_ferraris.toml", registry)
    acc, gyr = rec.device()["accel"], rec.device()["gyro"]
    assert acc.num_rows == gyr.num_rows == 10376
    rows = first_rows(shared_data / "imucal" / "example_ferraris_session.csv", 3)
    for i, row in enumerate(rows):
        for axis in "xyz":
            assert acc.column(axis)[i].as_py() == float(row[f"acc_{axis}"])
            assert gyr.column(axis)[i].as_py() == pytest.approx(float(row[f"gyr_{axis}"]) * DEG,
                                                                rel=1e-15)
    t = acc.column("t_ns").to_numpy()
    assert t[1] == 9_765_625 and t[-1] == round(10375 * 1e9 / 102.4)  # 102.4 Hz, no stamps
    sections = rec.meta["sections"]
    assert sorted(sections) == sorted(["x_p", "x_a", "y_p", "y_a", "z_p", "z_a",
                                       "x_rot", "y_rot", "z_rot"])
    assert sections["x_p"] == {"start": 540, "end": 1271, "t_start_ns": t[540],
                               "t_end_ns": t[1270], "stream": "accel"}
    assert rec.meta["meta"]["reference_gravity_mps2"] == 9.81


def test_tomisuarez2_nominal_mpu6050_scales(shared_data, registry):
    rec = read_recording(SESSIONS / "tomisuarez2.toml", registry)
    acc, gyr = rec.device()["accel"], rec.device()["gyro"]
    assert acc.num_rows == 10245  # 10250 lines - 4 settings lines - header
    row = first_rows(shared_data / "tomisuarez2_mpu6050" / "calibration data" /
                     "example_data_calibration.csv", 1, skip=4)[0]
    assert row == {"ax": "-12", "ay": "-812", "az": "15032", "gx": "-447", "gy": "156",
                   "gz": "-86"}
    assert acc.column("z")[0].as_py() == pytest.approx(15032 / 16384 * G0, rel=1e-15)
    assert gyr.column("x")[0].as_py() == pytest.approx(-447 / 131 * DEG, rel=1e-15)
    assert acc.column("t_ns")[1].as_py() == 10_000_000


def test_imu_tk_xsens_keeps_raw_counts(shared_data, registry):
    rec = read_recording(SESSIONS / "imu_tk_xsens.toml", registry)
    acc = rec.device()["accel"]
    assert acc.num_rows == 51175
    # first line of xsens_acc.mat: 2.9840000e-02 3.3108000e+04 3.3329000e+04 3.6429000e+04
    assert acc.column("t_ns")[0].as_py() == 29_840_000
    assert [acc.column(a)[0].as_py() for a in "xyz"] == [33108.0, 33329.0, 36429.0]
    assert acc.schema.metadata[b"imupipe.source_unit"] == b"counts"
    assert acc.schema.metadata[b"imupipe.raw_unit"] == b"counts"  # calibration.json raw_units


def test_sunsided_full_sphere_units(shared_data, registry):
    rec = read_recording(SESSIONS / "sunsided_full_sphere.toml", registry)
    dev = rec.device()
    assert {k: t.num_rows for k, t in dev.items()} == {"accel": 10528, "gyro": 10528,
                                                     "mag": 8190, "temperature": 10528}
    # first buffer columns (h5py): accel [t, x, y, z] = [0.00846.., 0.05200195, -0.18261719, -1.01074219] g
    assert dev["accel"].column("z")[0].as_py() == pytest.approx(-1.01074219 * G0, rel=1e-8)
    assert dev["mag"].column("x")[0].as_py() == pytest.approx(0.2412844e-4, rel=1e-6)
    assert dev["gyro"].column("x")[0].as_py() == pytest.approx(10.0839695 * DEG, rel=1e-8)
    assert 24.5 < dev["temperature"].column("temperature")[0].as_py() < 25.1
    assert dev["accel"].column("t_ns")[0].as_py() == round(0.00846300555 * 1e9)


def test_ingest_a_manifest_from_the_command_line(shared_data, tmp_path, capsys):
    out = tmp_path / "tables"
    assert main(["ingest", str(SESSIONS / "imucal_ferraris.toml"), "--out", str(out)]) == 0
    assert sorted(p.name for p in (out / "imu").iterdir()) == ["accel.arrow", "gyro.arrow"]


# --------------------------------------------------------------------------- format features


def test_units_scale_offset_and_time_units(tmp_path, registry):
    write(tmp_path / "log.csv", "ms;ax;ay;az;tk\n0;100;200;300;298.15\n20;101;201;301;299.15\n")
    manifest = write(tmp_path / "session.toml", """
[session]
name = "units"
[[streams]]
stream = "accel"
file = "log.csv"
delimiter = ";"
columns = { t = "ms", x = "ax", y = "ay", z = "az" }
time_unit = "ms"
unit = "mg"
scale = [1.0, -1.0, 2.0]
offset = 100.0
[[streams]]
stream = "temperature"
file = "log.csv"
delimiter = ";"
columns = { t = "ms", temperature = "tk" }
time_unit = "ms"
unit = "K"
""")
    rec = read_recording(manifest, registry)
    acc = rec.device()["accel"]
    assert acc.column("t_ns").to_pylist() == [0, 20_000_000]
    assert acc.column("x").to_pylist() == pytest.approx([0.0, 1e-3 * G0])
    assert acc.column("y").to_pylist() == pytest.approx([-100e-3 * G0, -101e-3 * G0])
    assert acc.column("z").to_pylist() == pytest.approx([400e-3 * G0, 402e-3 * G0])
    assert rec.device()["temperature"].column("temperature").to_pylist() == pytest.approx(
        [25.0, 26.0])


def test_si_streams_carry_no_raw_unit(tmp_path, registry):
    write(tmp_path / "acc.csv", "t,x,y,z\n0,1,2,3\n0.01,1,2,3\n")
    manifest = write(tmp_path / "session.toml", '[session]\nname = "g"\n'
                     '[[streams]]\nstream = "accel"\nfile = "acc.csv"\nunit = "g"\n')
    meta = read_recording(manifest, registry).device()["accel"].schema.metadata
    assert b"imupipe.raw_unit" not in meta  # converted to m/s^2: no raw unit to state


@pytest.mark.parametrize("unit, t0, t1", [("s", "1700000000123456789", "1700000000133456789"),
                                          ("ms", "1e300", "2e300")])
def test_time_column_overflowing_int64_ns_names_the_fix(tmp_path, registry, unit, t0, t1):
    write(tmp_path / "acc.csv", f"time,x,y,z\n{t0},1,2,3\n{t1},1,2,3\n")
    manifest = write(tmp_path / "session.toml", '[session]\nname = "ns"\n[[streams]]\n'
                     'stream = "accel"\nfile = "acc.csv"\n'
                     'columns = { t = "time", x = "x", y = "y", z = "z" }\n'
                     f'time_unit = "{unit}"\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy RuntimeWarning on the way
        with pytest.raises(ReaderError, match=(
            rf"acc.csv: time column 'time' with time_unit '{unit}' overflows int64 nanoseconds "
            r".*is the column in ns\? set time_unit")):
            read_recording(manifest, registry)


def test_delegates_names_the_readers_a_manifest_uses(tmp_path):
    manifest = write(tmp_path / "session.toml", '[session]\nname = "d"\n'
                     '[[streams]]\nstream = "accel"\nfile = "a.csv"\nreader = "csv"\n'
                     '[[streams]]\nstream = "gyro"\nfile = "g.csv"\n')
    assert ManifestReader().delegates(manifest) == ["csv"]


def test_lsb_per_unit_and_samples_time_and_devices(tmp_path, registry):
    write(tmp_path / "a.csv", "n,x,y,z\n0,131,0,-131\n1,262,0,0\n")
    manifest = write(tmp_path / "session.toml", """
[session]
name = "two"
[[streams]]
stream = "gyro"
file = "a.csv"
columns = { t = "n", x = "x", y = "y", z = "z" }
time_unit = "samples"
rate_hz = 50.0
unit = "deg/s"
lsb_per_unit = 131.0
[[streams]]
stream = "gyro"
device = "second"
file = "a.csv"
unit = "rpm"
rate_hz = 10
""")
    rec = read_recording(manifest, registry)
    g = rec.devices["imu"]["gyro"]
    assert g.column("t_ns").to_pylist() == [0, 20_000_000]
    assert g.column("x").to_pylist() == pytest.approx([DEG, 2 * DEG])
    second = rec.devices["second"]["gyro"]  # positional default columns: x, y, z at 10 Hz
    assert second.column("t_ns").to_pylist() == [0, 100_000_000]
    assert second.column("x").to_pylist() == pytest.approx([0.0, 2 * math.pi / 60])


def test_reuses_a_registered_reader(tmp_path):
    write(tmp_path / "canon.csv", "t_ns,mag_x,mag_y,mag_z\n0,1e-5,2e-5,3e-5\n7,1e-5,2e-5,4e-5\n")
    manifest = write(tmp_path / "session.toml", """
[session]
name = "via-reader"
[[streams]]
stream = "mag"
file = "canon.csv"
reader = "csv"
scale = 2.0
""")
    rec = ManifestReader().read(manifest)
    assert rec.device()["mag"].column("z").to_pylist() == pytest.approx([6e-5, 8e-5])


def test_inline_sections_in_seconds(tmp_path, registry):
    write(tmp_path / "a.csv", "x,y,z\n" + "1,2,3\n" * 100)
    manifest = write(tmp_path / "session.toml", """
[session]
name = "sec"
[[streams]]
stream = "accel"
file = "a.csv"
rate_hz = 10
[sections]
unit = "s"
items = { rest = [1.0, 2.5] }
""")
    rec = read_recording(manifest, registry)
    assert rec.meta["sections"]["rest"] == {"start": 10, "end": 25, "t_start_ns": 1_000_000_000,
                                            "t_end_ns": 2_400_000_000, "stream": "accel"}


def test_zero_padding_repair_only_when_declared(shared_data, tmp_path, registry):
    mat = (shared_data / "sunsided_mpu6050_hmc5883l" / "data" / "set-1" /
           "unmoved-z-pointing-left" / "mpu6050_gyroscope.mat")
    text = f"""
[session]
name = "set1"
[[streams]]
stream = "gyro"
file = "{mat}"
unit = "deg/s"
"""
    broken = write(tmp_path / "broken.toml", text)
    with pytest.raises(ReaderError, match="time goes backwards at sample 6280"):
        read_recording(broken, registry)
    repaired = write(tmp_path / "repaired.toml", text + 'repair = ["drop_zero_padding"]\n')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = read_recording(repaired, registry)
    assert rec.device()["gyro"].num_rows == 6280
    assert any("dropped 720 trailing all-zero rows" in str(w.message) for w in caught)


# --------------------------------------------------------------------------- errors


MINIMAL = """
[session]
name = "bad"
[[streams]]
stream = "accel"
file = "a.csv"
rate_hz = 10
"""

BAD = {
    "unknown_key": (MINIMAL + "colums = { x = 'a' }\n",
                    "streams[0].colums: unknown key; did you mean 'columns'?"),
    "bad_unit": (MINIMAL + "unit = 'deg/s'\n",
                 "streams[0]: unit 'deg/s' does not fit stream 'accel'; known: m/s^2"),
    "no_time": (MINIMAL.replace("rate_hz = 10", "columns = { x = 'x', y = 'y', z = 'z' }"),
                "streams[0]: no time column: give columns.t or rate_hz"),
    "no_session": ("[[streams]]\nstream='accel'\nfile='a.csv'\n[session]\n", "session.name: missing required key"),
    "bad_stream": (MINIMAL.replace('stream = "accel"', 'stream = "baro"'), "streams[0].stream"),
    "toml_syntax": ("[session]\nname = \n", "not valid TOML"),
    "missing_file": (MINIMAL.replace("a.csv", "nope.csv"), "streams[0].file: no such file"),
    "duplicate": (MINIMAL + MINIMAL.split("\n", 3)[3], "a second 'accel' stream for device 'imu'"),
    "section_range": (MINIMAL + "[sections]\nitems = { a = [5, 50] }\n",
                      "sections: 'a' = [5, 50) is outside the 3 samples"),
    "time_twice": (MINIMAL + "columns = { t = 'x', x = 'x', y = 'y', z = 'z' }\n",
                   "both columns.t and rate_hz"),
    "both_scales": (MINIMAL + "scale = 2.0\nlsb_per_unit = 3.0\n", "not both"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_manifest_is_one_line_naming_file_and_key(case, tmp_path, capsys):
    text, expected = BAD[case]
    write(tmp_path / "a.csv", "x,y,z\n1,2,3\n1,2,3\n1,2,3\n")
    manifest = write(tmp_path / "session.toml", text)
    out = tmp_path / "out"
    assert main(["ingest", str(manifest), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(manifest) in err and expected in err, err
    assert not out.exists()


def test_sniff_needs_a_session_table(tmp_path):
    reader = ManifestReader()
    yes = write(tmp_path / "s.toml", "# c\n[session]\nname='x'\n")
    no = write(tmp_path / "p.toml", "name = 'pipeline'\n[stages.a]\nuses='x'\n")
    assert reader.sniff(yes, b"") and not reader.sniff(no, b"")


def test_config_error_type(tmp_path):
    manifest = write(tmp_path / "session.toml", "streams = []\n[session]\nname='x'\n")
    with pytest.raises(ConfigError, match="streams: List should have at least 1 item"):
        ManifestReader().read(manifest)


# --------------------------------------------------------------------------- golden summaries


GOLDEN = Path(__file__).resolve().parent / "golden"


def summary(recording) -> dict:
    """Row count, first/last stamp and column means of every table: a compact fingerprint."""
    out = {}
    for device, streams in sorted(recording.devices.items()):
        for stream, table in sorted(streams.items()):
            t = table.column("t_ns").to_numpy()
            out[f"{device}/{stream}"] = {
                "rows": table.num_rows, "t_first_ns": int(t[0]), "t_last_ns": int(t[-1]),
                "mean": {c: float(np.mean(table.column(c).to_numpy()))
                         for c in table.column_names if c != "t_ns"},
            }
    return out


@pytest.mark.filterwarnings("ignore:.*trailing all-zero rows.*:UserWarning")
@pytest.mark.parametrize("name", ["imucal_ferraris", "imu_tk_xsens", "tomisuarez2",
                                  "sunsided_full_sphere", "sunsided_set1_unmoved_z_left"])
def test_example_sessions_match_golden(name, shared_data, registry, update_golden):
    got = summary(read_recording(SESSIONS / f"{name}.toml", registry))
    path = GOLDEN / f"{name}.json"
    if update_golden:
        path.parent.mkdir(exist_ok=True)
        path.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
    expected = json.loads(path.read_text())
    assert got.keys() == expected.keys()
    for key, want in expected.items():
        have = got[key]
        assert (have["rows"], have["t_first_ns"], have["t_last_ns"]) == (
            want["rows"], want["t_first_ns"], want["t_last_ns"]), key
        assert have["mean"] == pytest.approx(want["mean"], rel=1e-12, abs=1e-18), key


def test_every_reader_here_is_a_reader():
    from imupipe.components import Reader
    from imupipe.readers import csv as csv_module
    from imupipe.readers import manifest, matlab, ulog

    for module in (csv_module, manifest, matlab, ulog):
        for reader in module.COMPONENTS:
            assert isinstance(reader, Reader), reader

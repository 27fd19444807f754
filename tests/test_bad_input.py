"""Issue 12: bad input is one line on stderr and exit status 2, never a traceback."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from imupipe import cli

HEADER = "t_ns,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z"


def write_csv(path, n=300, rate_hz=100.0, t_scale=1.0, value_scale=1.0, text_hook=None):
    rng = np.random.default_rng(0)
    t = (np.arange(n) * (1e9 / rate_hz) * t_scale).astype(np.int64) + 1_000_000_000
    v = np.column_stack([[0.0] * n, [0.0] * n, [9.81] * n, [0.0] * n, [0.0] * n, [0.0] * n])
    v = (v + 0.01 * rng.standard_normal(v.shape)) * value_scale
    lines = [HEADER] + [f"{ti}," + ",".join(repr(float(x)) for x in row) for ti, row in zip(t, v)]
    text = "\n".join(lines) + "\n"
    path.write_text(text_hook(text) if text_hook else text, encoding="utf-8")
    return path


def run(capsys, *argv):
    code = cli.main([*map(str, argv), "--quiet"])
    err = capsys.readouterr().err
    return code, err


def assert_one_line(code, err, *needles):
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("imupipe "), err
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_fifo_and_symlink_loop_as_session(tmp_path, capsys):
    fifo = tmp_path / "s.csv"
    os.mkfifo(fifo)
    loop = tmp_path / "loop.csv"
    loop.symlink_to(loop)
    for command in ("ingest", "run"):
        assert_one_line(*run(capsys, command, fifo, "--out", tmp_path / "o"), "FIFO")
        assert_one_line(*run(capsys, command, loop, "--out", tmp_path / "o"), "loop of symbolic")


def test_csv_with_bom_and_trailing_blank_lines_is_read(tmp_path, capsys):
    path = write_csv(tmp_path / "s.csv", text_hook=lambda t: "\ufeff" + t + "\n\n  \n")
    code, err = run(capsys, "ingest", path, "--out", tmp_path / "o")
    assert code == 0, err
    assert (tmp_path / "o" / "imu" / "accel.arrow").is_file()


@pytest.mark.parametrize("t_scale, rate", [(100.0, "1 Hz"), (1000.0, "0.1 Hz")])
def test_slow_or_mis_scaled_time_is_one_line(tmp_path, capsys, t_scale, rate):
    path = write_csv(tmp_path / "s.csv", t_scale=t_scale)
    assert_one_line(*run(capsys, "run", path, "--out", tmp_path / "o"), f"sample rate {rate}",
                    "time stamps")


def test_absurd_values_are_one_line(tmp_path, capsys):
    path = write_csv(tmp_path / "s.csv", value_scale=1e300)
    assert_one_line(*run(capsys, "ingest", path, "--out", tmp_path / "o"), "beyond any sensor")


def test_deep_toml_pipeline_and_manifest(tmp_path, capsys):
    deep = "x = " + "[" * 2000 + "]" * 2000 + "\n"
    pipeline = tmp_path / "p.toml"
    pipeline.write_text(deep)
    session = write_csv(tmp_path / "s.csv")
    assert_one_line(*run(capsys, "run", session, "--pipeline", pipeline, "--out", tmp_path / "o"),
                    "nested too deeply")
    manifest = tmp_path / "m" / "session.toml"
    manifest.parent.mkdir()
    manifest.write_text('[session]\nname = "x"\n[meta]\n' + deep)
    assert_one_line(*run(capsys, "ingest", manifest, "--out", tmp_path / "o"), "nested too deeply")


def _manifest(folder, text):
    folder.mkdir(exist_ok=True)
    write_csv(folder / "a.csv")
    path = folder / "session.toml"
    path.write_text('[session]\nname = "x"\n' + text)
    return path


def test_self_referencing_manifest(tmp_path, capsys):
    path = _manifest(tmp_path / "m",
                     '[[streams]]\nstream = "accel"\nfile = "session.toml"\nreader = "session"\n')
    assert_one_line(*run(capsys, "ingest", path, "--out", tmp_path / "o"), "refers to itself")


def test_nan_section_bounds(tmp_path, capsys):
    path = _manifest(tmp_path / "m", '[[streams]]\nstream = "accel"\nfile = "a.csv"\n'
                     'time_unit = "ns"\n[sections]\nitems = { rest = [nan, 50] }\n')
    assert_one_line(*run(capsys, "ingest", path, "--out", tmp_path / "o"), "'rest'", "finite")


def test_triad_file_offered_as_temperature(tmp_path, capsys):
    path = _manifest(tmp_path / "m", '[[streams]]\nstream = "accel"\nfile = "a.csv"\n'
                     'time_unit = "ns"\n[[streams]]\nstream = "temperature"\nfile = "a.csv"\n'
                     'time_unit = "ns"\n')
    assert_one_line(*run(capsys, "ingest", path, "--out", tmp_path / "o"),
                    "offered as a temperature stream", "columns")


def test_absurd_skip_lines_is_bounded(tmp_path, capsys):
    path = _manifest(tmp_path / "m", '[[streams]]\nstream = "accel"\nfile = "a.csv"\n'
                     'skip_lines = 100000000\n')
    assert_one_line(*run(capsys, "ingest", path, "--out", tmp_path / "o"), "skip_lines")


def test_error_line_truncates_echoed_values(tmp_path, capsys):
    path = write_csv(tmp_path / "s.csv",
                     text_hook=lambda t: t.replace("\n", "\n" + "9" * 5_000_000 + "x,1,2,3,4,5,6\n", 1))
    code, err = run(capsys, "ingest", path, "--out", tmp_path / "o")
    assert_one_line(code, err, "s.csv", "characters cut", "fix or remove that row")
    assert len(err) < 2000


def test_numpy_warnings_never_precede_the_error_line(tmp_path, capsys, monkeypatch):
    from imupipe.pipeline import runner

    session = write_csv(tmp_path / "s.csv")

    def failing_segment(inputs, params, solver):
        np.log(np.zeros(3))  # RuntimeWarning: divide by zero
        return np.linalg.inv(np.zeros((3, 3)))  # LinAlgError: singular matrix

    real = runner._run_node

    def patched(node, *a, **k):
        import dataclasses

        stage = dataclasses.replace(node.stage, func=failing_segment)
        return real(dataclasses.replace(node, stage=stage), *a, **k)

    monkeypatch.setattr(runner, "_run_node", patched)
    code, err = run(capsys, "run", session, "--out", tmp_path / "o")
    assert_one_line(code, err, "LinAlgError", "dead, saturated or constant axes")


def test_internal_error_is_one_line_exit_1(tmp_path, capsys, monkeypatch):
    from imupipe.pipeline import api

    def boom(*a, **k):
        raise KeyError("internal")

    monkeypatch.setattr(api, "run_sessions", boom)
    code = cli.main(["run", str(tmp_path / "x.csv"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1 and "internal error: KeyError" in err
    assert "Traceback" not in err


@pytest.mark.skipif(sys.platform == "win32" or os.geteuid() == 0, reason="root writes anywhere")
def test_unwritable_out(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    path = write_csv(tmp_path / "s.csv")
    assert_one_line(*run(capsys, "ingest", path, "--out", ro / "o"), "--out")


def test_full_disk_is_one_line(tmp_path, capsys, monkeypatch):
    import errno

    import imupipe.ingest

    def full(path, table):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(imupipe.ingest, "write_arrow", full)
    path = write_csv(tmp_path / "s.csv")
    assert_one_line(*run(capsys, "ingest", path, "--out", tmp_path / "o"), "No space left",
                    "accel.arrow")


def test_missing_imu_stream_is_named(tmp_path, capsys):
    rng = np.random.default_rng(0)
    t = 1_000_000_000 + np.arange(600) * 10_000_000
    mag = 2e-5 + 1e-7 * rng.standard_normal((600, 3))
    rows = [f"{ti},{float(m[0])!r},{float(m[1])!r},{float(m[2])!r},25.0" for ti, m in zip(t, mag)]
    path = tmp_path / "magonly.csv"
    path.write_text("t_ns,mag_x,mag_y,mag_z,temperature\n" + "\n".join(rows) + "\n")
    assert_one_line(*run(capsys, "run", path, "--out", tmp_path / "o"),
                    "no accel or gyro stream", "sensor_msgs/Imu")

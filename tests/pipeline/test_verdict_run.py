"""The verdict through ``imupipe run``: in calibration.json, in report.md, printed; ``--strict``.

A short simulated gimbal session (about 1 s of fitting) through method B's stages
and the joint refinement; the silent-wrong cases of issues 10 and 12 built from it
by swapping two gyro columns or flipping the sign of an accelerometer column.
"""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow.compute as pc
import pyarrow.csv as pcsv
import pytest

from imupipe.cli import main
from imupipe.sim.api import simulate_recording, write_csv

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("verdict")
    rec, _ = simulate_recording("gimbal", {}, 4, grid_deg=60.0, n_rotations=12, rest_s=3.5)
    clean = folder / "clean.csv"
    write_csv(clean, rec)
    table = pcsv.read_csv(clean)

    def variant(name: str, **cols) -> Path:
        t = table
        for col, values in cols.items():
            t = t.set_column(t.column_names.index(col), col, values)
        path = folder / f"{name}.csv"
        pcsv.write_csv(t, path)
        return path

    # the pipeline without the residual map (fast); reports: the control set and the rests
    text = (PIPELINES / "gimbal-optimization.toml").read_text()
    head = text.split("[stages.map]")[0]
    pipeline = folder / "fast.toml"
    pipeline.write_text(head + '[export]\ncalibration = ["accel.calibration", "gyro.calibration", '
                        '"refine.calibration"]\nreports = ["control.control", "rests.rests"]\n')
    return {
        "pipeline": pipeline, "clean": clean,
        "swapped": variant("swapped", gyro_x=table["gyro_y"], gyro_y=table["gyro_x"]),
        "flipped": variant("flipped", accel_y=pc.negate(table["accel_y"])),
    }


def run(sessions, name: str, out: Path, capsys, *extra: str) -> tuple[int, str, dict]:
    code = main(["run", str(sessions[name]), "--pipeline", str(sessions["pipeline"]), "--out", str(out),
                 "--quiet", *extra])
    printed = capsys.readouterr().out
    doc = json.loads((out / name / "calibration.json").read_text())
    return code, printed, doc


def test_clean_session_passes_and_the_verdict_is_everywhere(sessions, tmp_path, capsys):
    code, printed, doc = run(sessions, "clean", tmp_path, capsys, "--strict")
    verdict = doc["verdict"]
    assert code == 0 and verdict["status"] == "pass", verdict["reasons"]
    assert {"status", "reasons"} <= set(verdict)  # spec/contracts.md
    assert printed.splitlines()[1].startswith("verdict: pass")
    report = (tmp_path / "clean" / "report.md").read_text()
    assert "## Verdict: pass" in report and "| control | pass |" in report


def test_swapped_gyro_axes_fail_and_strict_exits_3(sessions, tmp_path, capsys):
    code, printed, doc = run(sessions, "swapped", tmp_path, capsys)
    assert code == 0 and doc["verdict"]["status"] == "fail"
    assert "gyro: det M" in printed and "left-handed" in printed
    code, _, _ = run(sessions, "swapped", tmp_path, capsys, "--strict")
    assert code == 3


def test_sign_flipped_accel_axis_fails(sessions, tmp_path, capsys):
    """The gyro absorbs the flip as a proper half turn: det M > 0, the frames check catches it."""
    code, printed, doc = run(sessions, "flipped", tmp_path, capsys, "--strict")
    assert code == 3 and doc["verdict"]["status"] == "fail"
    assert "gyro axes turned 180 deg from the accelerometer's" in printed


def test_batch_shows_verdicts_and_strict_exits_3(sessions, tmp_path, capsys):
    code = main(["batch", str(sessions["swapped"]), "--pipeline", str(sessions["pipeline"]), "--out",
                 str(tmp_path), "--jobs", "1", "--quiet", "--strict"])
    printed = capsys.readouterr().out
    assert code == 3 and "ok (fail)" in printed

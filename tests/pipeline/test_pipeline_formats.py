"""The pipeline on real session formats (canonical CSV, ROS 2 MCAP): same calibration as the toy file."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pipeline_toys import ArrowSessionReader, write_session

from imupipe.pipeline.api import batch, run_sessions

pytest.importorskip("imupipe.readers.csv")
pytest.importorskip("imupipe.readers.mcap")
mcap_writer = pytest.importorskip("imupipe.writers.mcap")
import pipeline_real_readers  # noqa: E402  (after the skips: it imports the readers)


def _write_csv(path, recording):
    streams = recording.device()
    t = streams["accel"].column("t_ns").to_numpy()
    cols = {"t_ns": t}
    for s in ("accel", "gyro", "mag"):
        for a in "xyz":
            cols[f"{s}_{a}"] = streams[s].column(a).to_numpy()
    cols["temperature"] = streams["temperature"].column("temperature").to_numpy()
    lines = [",".join(cols)]
    for i in range(len(t)):
        lines.append(",".join(str(int(v[i])) if k == "t_ns" else repr(float(v[i])) for k, v in cols.items()))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def formats(tmp_path):
    toy = write_session(tmp_path / "toy.arrowsession", seed=3)
    recording = ArrowSessionReader().read(toy)
    csv = _write_csv(tmp_path / "lab.csv", recording)
    mcap = tmp_path / "rig.mcap"
    mcap_writer.write_mcap(mcap, recording)
    return toy, csv, mcap


def test_csv_and_mcap_sessions_give_the_same_calibration(tmp_path, toy_registry, toy_pipeline, formats):
    registry, counter = toy_registry(pipeline_real_readers)
    out = tmp_path / "out"
    run_sessions(list(formats), toy_pipeline, out, quiet=True, registry=registry)
    docs = {p.stem: json.loads((out / p.stem / "calibration.json").read_text()) for p in formats}
    assert set(docs) == {"toy", "lab", "rig"}
    for sensor in ("accel", "gyro", "mag"):
        for other in ("lab", "rig"):
            np.testing.assert_allclose(docs[other][sensor]["b0"], docs["toy"][sensor]["b0"], rtol=1e-12, atol=0)
    assert counter.ran.count("accel") == 3


def test_batch_over_a_folder_of_csv_and_mcap(tmp_path, toy_pipeline, formats, capsys):
    from conftest import TOY_SPEC

    spec = type(TOY_SPEC)((*TOY_SPEC.plugins, "pipeline_real_readers"), entry_points=False)
    folder = formats[0].parent
    failures = batch([str(folder)], toy_pipeline, tmp_path / "out", "local", 2, quiet=True, plugins=spec)
    assert failures == []
    assert "3 ok, 0 failed" in capsys.readouterr().out

"""The pipeline on real session formats (canonical CSV, ROS 2 MCAP): same calibration."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pipeline_toys import ArrowSessionReader, write_session

from imupipe.pipeline.api import batch, run_sessions

pytest.importorskip("imupipe.readers.csv")
pytest.importorskip("imupipe.readers.mcap")
mcap_writer = pytest.importorskip("imupipe.writers.mcap")
import pipeline_real_readers  # after the skips: it imports the readers


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
        lines.append(
            ",".join(str(int(v[i])) if k == "t_ns" else repr(float(v[i])) for k, v in cols.items())
        )
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


def test_csv_and_mcap_sessions_give_the_same_calibration(
    tmp_path, toy_registry, toy_pipeline, formats
):
    registry, counter = toy_registry(pipeline_real_readers)
    out = tmp_path / "out"
    run_sessions(list(formats), toy_pipeline, out, quiet=True, registry=registry)
    docs = {p.stem: json.loads((out / p.stem / "calibration.json").read_text()) for p in formats}
    assert set(docs) == {"toy", "lab", "rig"}
    for sensor in ("accel", "gyro", "mag"):
        for other in ("lab", "rig"):
            np.testing.assert_allclose(
                docs[other][sensor]["b0"], docs["toy"][sensor]["b0"], rtol=1e-12, atol=0
            )
    assert counter.ran.count("accel") == 3


def test_batch_over_a_folder_of_csv_and_mcap(tmp_path, toy_pipeline, formats, capsys):
    from pipeline_toys import TOY_SPEC

    spec = type(TOY_SPEC)((*TOY_SPEC.plugins, "pipeline_real_readers"), entry_points=False)
    folder = formats[0].parent
    failures = batch(
        [str(folder)], toy_pipeline, tmp_path / "out", "local", 2, quiet=True, plugins=spec
    )
    assert failures == []
    assert "3 ok, 0 failed" in capsys.readouterr().out


def test_input_device_picks_one_imu_of_a_multi_imu_mcap(tmp_path, toy_registry, toy_pipeline):
    from imupipe.components import Recording
    from imupipe.errors import ReaderError

    one = ArrowSessionReader().read(write_session(tmp_path / "a.arrowsession", seed=1, bias=0.1))
    two = ArrowSessionReader().read(write_session(tmp_path / "b.arrowsession", seed=2, bias=0.3))
    both = Recording("two", {"left": one.device(), "right": two.device()})
    mcap = tmp_path / "pair.mcap"
    mcap_writer.write_mcap(mcap, both)
    registry, _ = toy_registry(pipeline_real_readers)
    with pytest.raises(
        ReaderError, match=r'holds 2 IMUs \(left, right\); choose one with `device = "NAME"`'
    ):
        run_sessions([mcap], toy_pipeline, tmp_path / "out", quiet=True, registry=registry)
    assert not (tmp_path / "out" / "pair" / "calibration.json").exists()

    text = toy_pipeline.read_text().replace(
        "[stages.scaled]", '[input]\ndevice = "right"\n\n[stages.scaled]'
    )
    toy_pipeline.write_text(text)
    run_sessions([mcap], toy_pipeline, tmp_path / "out", quiet=True, registry=registry)
    doc = json.loads((tmp_path / "out" / "pair" / "calibration.json").read_text())
    np.testing.assert_allclose(doc["gyro"]["b0"], 0.3, atol=0.01)  # the right IMU's bias

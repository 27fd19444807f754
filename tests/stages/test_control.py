"""Validation B: control-set gravity error before and after calibration; the split stage."""

from __future__ import annotations

import numpy as np
import pytest
from method_b_synth import make_session, session_tables
from pydantic import ValidationError

from imupipe import schemas
from imupipe.models import TriadCalibration, triads_to_table
from imupipe.observations import Rests, Turns
from imupipe.stages.control import SplitParams, control_errors, split_control, validate_control

NOISE_DEG = 0.1  # per-turn gravity mismatch from the synthetic noise is ~0.03 deg


def _truth(s):
    return (TriadCalibration("accel", np.linalg.inv(s.S_accel), s.b_accel),
            TriadCalibration("gyro", np.linalg.inv(s.S_gyro), s.b_gyro))


def test_true_calibration_leaves_only_noise():
    s = make_session(31, n_rests=20)
    err, rot = control_errors(*_truth(s), s.rests, s.turns)
    assert np.degrees(err).max() < NOISE_DEG
    assert np.degrees(rot).min() > 20.0  # the turns really turn


def test_validate_control_table_before_and_after():
    s = make_session(32, n_rests=20)
    accel, gyro = _truth(s)
    out = validate_control({**session_tables(s), "accel_calibration": triads_to_table([accel]),
                            "gyro_calibration": triads_to_table([gyro])}, None)
    table = out["control"]
    schemas.check(table, "control_errors")
    before = table.column("error_before_deg").to_numpy()
    after = table.column("error_after_deg").to_numpy()
    assert after.max() < NOISE_DEG
    assert np.sqrt(np.mean(before**2)) > 10 * np.sqrt(np.mean(after**2))
    assert float(table.schema.metadata[b"imupipe.rms_after_deg"]) == pytest.approx(
        np.sqrt(np.mean(after**2)))


def test_split_interleaved_holds_out_every_nth_turn():
    s = make_session(33, n_rests=21)
    out = split_control(session_tables(s), SplitParams(every=4))
    cal, ctl = out["turns"], out["control_turns"]
    assert cal.num_rows + ctl.num_rows == 20 and ctl.num_rows == 5
    assert set(ctl.column("rest_before").to_pylist()) == {3, 7, 11, 15, 19}
    schemas.check(ctl, "turns")


def test_split_by_time_renumbers_rests():
    s = make_session(34, n_rests=20)
    tables = session_tables(s)
    out = split_control(tables, SplitParams(mode="time", fraction=0.3))
    for prefix in ("", "control_"):
        rests = Rests.from_table(out[f"{prefix}rests"])
        turns = Turns.from_tables(out[f"{prefix}turns"], tables["gyro"], rests.t0_ns)
        assert len(turns) == len(rests) - 1
        assert turns.before.max() < len(rests) and turns.after.max() < len(rests)
        err, _ = control_errors(*_truth(s), rests, turns)
        assert np.degrees(err).max() < NOISE_DEG  # turns still join the right rests


def test_split_rejects_bad_settings():
    # bounds are checked when the params are validated (config time), not inside the stage
    with pytest.raises(ValidationError, match="every"):
        SplitParams(every=1)
    with pytest.raises(ValidationError, match="fraction"):
        SplitParams(mode="time", fraction=1.0)

"""A small noise-free gimbal session and the per-sample model fitted to it, shared by the
tests of the catalogue's columns (``test_select``) and the structure library (``test_library``)."""

from __future__ import annotations

import numpy as np
import pytest
from forward_synth import G, noise_free_imu, rests_from_truth, small_gimbal

from imupipe.diagnosis.forward import JointModel, MotionAccel, Noise, Start
from imupipe.diagnosis.linearised import fit

SEED = 3


def _model(out, truth):
    rests, turns = rests_from_truth(out, truth)
    cal = truth.calibration
    start = Start(np.linalg.inv(cal["accel"].M), cal["accel"].b0, cal["gyro"].M, cal["gyro"].b0,
                  cal["accel"].k, cal["gyro"].k)
    noise = Noise(np.eye(3) * 5e-3**2, np.eye(3) * 3.5e-4**2, np.full(3, 1e-9), np.full(3, 1e-10))
    acc = MotionAccel.select(out.t, out.raw["accel"], rests, turns)
    return JointModel(rests, turns, G, start, noise, fit_k=True, accel=acc,
                      temperature=(out.t, out.temperature)), rests, turns


@pytest.fixture(scope="session")
def fitted():
    """(imu, out, truth, model, rests, turns, lin) of a gimbal session warming a few degC in a minute."""
    imu = noise_free_imu(SEED)
    imu["thermal"] = {**imu["thermal"], "self_heating_C": 40.0, "tau_s": 60.0}  # a few degC in a minute
    out, truth = small_gimbal(SEED, imu)
    model, rests, turns = _model(out, truth)
    return imu, out, truth, model, rests, turns, fit(model, max_iter=5)



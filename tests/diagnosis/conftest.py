"""A small noise-free gimbal session and the per-sample model fitted to it, shared by the
tests of the catalogue's columns (``test_select``) and the structure library (``test_library``)."""

from __future__ import annotations

import pytest
from forward_synth import joint_model, noise_free_imu, small_gimbal

from imupipe.diagnosis.linearised import fit

SEED = 3


@pytest.fixture(scope="session")
def fitted():
    """(imu, out, truth, model, rests, turns, lin) of a gimbal session warming a few degC in a minute."""
    imu = noise_free_imu(SEED)
    imu["thermal"] = {**imu["thermal"], "self_heating_C": 40.0, "tau_s": 60.0}  # a few degC in a minute
    out, truth = small_gimbal(SEED, imu)
    model, rests, turns = joint_model(out, truth)
    return imu, out, truth, model, rests, turns, fit(model, max_iter=5)



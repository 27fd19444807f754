"""Method B solvers on the peers' real recordings (../shared/data), against their published numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imupipe.ingest import read_recording
from imupipe.observations import EllipsoidObservations, GyroObservations, Rests, Turns
from imupipe.plugins import make_registry
from imupipe.solvers.ellipsoid_svd import EllipsoidSVD, EllipsoidSVDParams
from imupipe.solvers.gyro_integration import GyroIntegration, GyroIntegrationParams
from imupipe.stages.segment import SegmentParams, segment

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "sessions"
IMUCAL_SCALE_TOL = 1e-4  # imucal prints 5 decimals
IMUCAL_BIAS_TOL = 2e-3  # m/s^2, imucal prints 3 decimals


def _xyz(table):
    return np.column_stack([table.column(c).to_numpy() for c in ("x", "y", "z")])


def test_imucal_six_poses_axis_aligned_fit_matches_imucal(shared_data):
    rec = read_recording(EXAMPLES / "imucal_ferraris.toml", make_registry())
    acc = _xyz(rec.device()["accel"])
    sec = rec.meta["sections"]
    poses = [slice(sec[p]["start"], sec[p]["end"]) for p in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")]
    y = np.array([acc[s].mean(axis=0) for s in poses])
    cov = np.array([np.cov(acc[s].T) / (s.stop - s.start) for s in poses])
    obs = EllipsoidObservations("accel", y, cov, np.full(6, np.nan), 9.81)
    fit = EllipsoidSVD().solve(obs, EllipsoidSVDParams(misalignment=False))
    np.testing.assert_allclose(1 / np.diag(fit.M), [0.99675, 1.00244, 1.02340], atol=IMUCAL_SCALE_TOL)
    np.testing.assert_allclose(fit.b0, [0.537, -0.616, 0.399], atol=IMUCAL_BIAS_TOL)


def test_tomisuarez2_ten_poses_and_a_clipping_gyro(shared_data):
    dev = read_recording(EXAMPLES / "tomisuarez2.toml", make_registry()).device()
    # the plain raw-variance test (no low-pass, no edge growth): the gyro is left out, its holds
    # are not still; the adaptive defaults split one nudged hold (68.8-71.7 s) in two
    seg = segment(dict(dev), SegmentParams(window_s=0.5, initial_rest_s=36.5, accel_threshold=10.0,
                                           gyro_threshold=1e9, min_rest_s=0.5, lowpass_s=0.0,
                                           edge_sigma=0.0), None)
    rests = Rests.from_table(seg["rests"])
    turns = Turns.from_tables(seg["turns"], dev["gyro"], rests.t0_ns)
    assert len(rests) == 10
    fit = EllipsoidSVD().solve(EllipsoidObservations("accel", rests.mean["accel"], rests.cov_of_mean("accel"),
                                                     rests.temperature, 9.80665), EllipsoidSVDParams())
    assert fit.details["dof"] == 1  # one position to spare: the fit cannot check itself
    x = (rests.mean["accel"] - fit.b0) @ fit.M.T
    g = x / np.linalg.norm(x, axis=1, keepdims=True)
    obs = GyroObservations(g, rests.mean["gyro"], rests.cov_of_mean("gyro"), turns)
    with pytest.warns(UserWarning, match=r"2 of 9 turns hold \d+ saturated gyro samples"):
        gf = GyroIntegration().solve(obs, GyroIntegrationParams())
    assert gf.details["turns"] == 7
    assert np.all(np.isfinite(np.diag(gf.cov)[:9]))
    # the MPU-6050 bias published by tomisuarez2 (-427.5, 147.9, -80.7 counts at 131 LSB per deg/s)
    np.testing.assert_allclose(np.degrees(gf.b0), np.array([-427.46, 147.95, -80.72]) / 131, atol=0.02)

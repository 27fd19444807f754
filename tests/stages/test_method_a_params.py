"""Method A stage parameters: reference-rest indices, bounds at config time, and residuals
that test the exported calibration (forward model)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from method_a_synth import B_ACC, S_ACC, G, unit_sphere
from pydantic import ValidationError

from imupipe.cli import main
from imupipe.components import BoundSolver
from imupipe.errors import ConfigError
from imupipe.models import triads_from_table
from imupipe.observations import Rests, TriadFit
from imupipe.sim.api import simulate, simulate_recording
from imupipe.solvers.ellipsoid_cholesky import EllipsoidCholesky, EllipsoidParams
from imupipe.solvers.gyro_rodrigues import GyroRodrigues, GyroRodriguesParams
from imupipe.stages import accel, gyro, segment, validate

SPHERE_RIG = Path(__file__).resolve().parents[2] / "pipelines" / "sphere-rig.toml"
BIAS_SHIFT_RAD_S = 0.005  # 0.29 deg/s: over a turn of seconds, a gravity error of ~1 deg


def rests_with_short_first(n: int = 40, y_up: int = 5, x_up: int = 6) -> Rests:
    """Noise-free accel rests; rest 0 is 1 s long (dropped by ``min_rest_s = 2``), the others
    5 s; rest ``y_up`` has the instrument Y up, rest ``x_up`` X up."""
    x = unit_sphere(n, np.random.default_rng(21)) * G
    x[y_up], x[x_up] = [0, G, 0], [G, 0, 0]
    y = x @ S_ACC.T + B_ACC
    t0 = np.arange(n) * 10.0
    length = np.where(np.arange(n) == 0, 1.0, 5.0)
    cov = np.tile(np.eye(3) * 1e-12, (n, 1, 1))  # noise-free, but a finite sigma
    return Rests(t0, t0 + length, np.full(n, 100), {"accel": y, "gyro": np.zeros((n, 3))},
                 {"accel": cov, "gyro": cov}, np.full(n, np.nan),
                 {"accel": np.full(n, 100), "gyro": np.full(n, 100)})


def accel_cal(params: accel.AccelParams, rests: Rests):
    out = accel.STAGE.func({"rests": rests.to_table()}, params,
                           BoundSolver(EllipsoidCholesky(), EllipsoidParams()))
    return triads_from_table(out["calibration"])[0]


def test_reference_rest_indices_count_all_rests_not_the_kept_ones():
    rests = rests_with_short_first()
    cal = accel_cal(accel.AccelParams(g_m_s2=G, y_up_rest=5, x_up_rest=6, min_rest_s=2.0), rests)
    assert np.allclose(cal.M @ S_ACC, np.eye(3), atol=1e-9)  # the frame of the true Y/X-up rests
    assert cal.details["reference_rests"]["y_up"] == 5


def test_a_short_reference_rest_stays_in_the_fit():
    rests = rests_with_short_first(y_up=0, x_up=6)
    cal = accel_cal(accel.AccelParams(g_m_s2=G, y_up_rest=0, x_up_rest=6, min_rest_s=2.0), rests)
    assert np.allclose(cal.M @ S_ACC, np.eye(3), atol=1e-9)


def test_x_up_without_y_up_is_a_config_error():
    with pytest.raises(ValidationError, match="x_up_rest / x_up_time_s given without y_up"):
        accel.AccelParams(x_up_rest=3)
    with pytest.raises(ValidationError, match="without y_up"):
        accel.AccelParams(x_up_time_s=12.0)


def test_reference_rest_out_of_range_names_the_valid_range():
    with pytest.raises(ConfigError, match=r"y_up_rest = 40 .*valid indices 0\.\.39"):
        accel_cal(accel.AccelParams(y_up_rest=40), rests_with_short_first())


# --------------------------------------------------------------------------- forward model


class ShiftedBias:
    """GyroRodrigues with ``b0`` moved by ``BIAS_SHIFT_RAD_S``: a wrong exported calibration."""

    name, kind, version, params = "shifted", "gyro", "1", GyroRodriguesParams

    def solve(self, obs, params):
        fit = GyroRodrigues().solve(obs, params)
        return TriadFit(fit.M, fit.b0 + BIAS_SHIFT_RAD_S, fit.cov, fit.details)


@pytest.fixture(scope="module")
def sim():
    rec, truth = simulate_recording("standard", None, 5, n_positions=40, warmup_s=60)
    d = dict(rec.device("imu"))
    seg = segment.STAGE.func(d, segment.SegmentParams(), None)
    ac = accel.STAGE.func({"rests": seg["rests"]},
                          accel.AccelParams(g_m_s2=truth.data["environment"]["g_m_s2"]),
                          BoundSolver(EllipsoidCholesky(), EllipsoidParams()))
    return d, seg, ac


def gyro_run(sim, solver):
    d, seg, ac = sim
    inputs = {"rests": seg["rests"], "turns": seg["turns"], "gyro": d["gyro"],
              "accel": ac["calibration"]}
    out = gyro.STAGE.func(inputs, gyro.GyroParams(), BoundSolver(solver, GyroRodriguesParams()))
    res = out["residuals"].filter(out["residuals"].column("kind").to_numpy(zero_copy_only=False)
                                  == "turn")
    turn_rms = float(np.sqrt(np.mean(np.square(np.array(res.column("residual").to_pylist())))))
    report = validate.STAGE.func({**inputs, "gyro_cal": out["calibration"]},
                                 validate.ValidateParams(), None)["report"]
    return turn_rms, float(np.sqrt(np.mean(report.column("gravity_error_after_deg").to_numpy() ** 2)))


def test_turn_residuals_and_validation_test_the_exported_bias(sim):
    good_res, good_val = gyro_run(sim, GyroRodrigues())
    bad_res, bad_val = gyro_run(sim, ShiftedBias())
    # the rests' own means would hide a wrong b0; the forward model cal.bias(T) shows it
    assert bad_res > 3 * good_res
    assert bad_val > 3 * good_val


def test_roll_turn_out_of_range_names_the_valid_range(sim):
    d, seg, ac = sim
    n = seg["turns"].num_rows
    with pytest.raises(ConfigError, match=rf"roll_turn = 999 .*valid indices 0\.\.{n - 1}"):
        gyro.STAGE.func({"rests": seg["rests"], "turns": seg["turns"], "gyro": d["gyro"],
                         "accel": ac["calibration"]}, gyro.GyroParams(roll_turn=999),
                        BoundSolver(GyroRodrigues(), GyroRodriguesParams()))


# --------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def session_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("session") / "s.csv"
    simulate("standard", {}, 3, path, True, params={"n_positions": 30, "warmup_s": 60})
    return path


BAD = [  # (replace this, with that, the key path the message must name)
    ("window_s = 1.0", "window_s = -1.0", "stages.rests.params.window_s"),
    ("min_rest_s = 3.0", "min_rest_s = 3.0\nnoise_quantile = 2.0", "stages.rests.params.noise_quantile"),
    ("detect_tol_deg = 2.0", "detect_tol_deg = 2.0\nx_up_rest = 3", "stages.accel.params"),
    ("solver_params = { p0 = 1.0 }", "solver_params = { p0 = -1.0 }",
     "stages.thermal.params.solver_params.p0"),
    ("tolerance_deg = 0.1", "tolerance_deg = 0.0", "stages.validate.params.tolerance_deg"),
    ("detect_roll_turn = true ", "roll_turn = 999\ndetect_roll_turn = true ", "roll_turn = 999"),
    ("detect_tol_deg = 2.0", "detect_tol_deg = 2.0\ny_up_rest = 300", "y_up_rest = 300"),
]


@pytest.mark.parametrize(("old", "new", "key"), BAD, ids=[b[2] for b in BAD])
def test_bad_params_exit_2_with_one_line_naming_the_key(old, new, key, session_csv, tmp_path, capsys):
    text = SPHERE_RIG.read_text()
    assert text.count(old) == 1
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace(old, new))
    code = main(["run", str(session_csv), "--pipeline", str(bad), "--out", str(tmp_path / "out"),
                 "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert key in err
    assert "Traceback" not in err and len(err.splitlines()) == 1, err

"""Round trips of every format exporter: write, parse with the target's own convention,
apply to raw data, compare with ``TriadCalibration.apply`` (to 1e-9).

Each ``*_correct`` function below is the target's correction as its own source code
states it (cited in ``imupipe/formats/<target>.py``), written independently of the
exporter. Parts a target cannot hold must appear in the file and in the log.
"""

from __future__ import annotations

import logging
import re

import numpy as np
import pyarrow as pa
import pytest
import yaml

from imupipe import schemas
from imupipe.formats import ardupilot, imu_calib, imu_tk, kalibr, px4
from imupipe.formats._common import FLU_FRD, ExportError
from imupipe.models import TriadCalibration, triads_to_table

RNG = np.random.default_rng(7)
R = FLU_FRD
TEMPS = (10.0, 30.0)  # the session's temperature range, degC


def close(a, b, tol=1e-9):
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a, b, rtol=0, atol=tol * max(1.0, float(np.abs(b).max())))


def triad(sensor, M, b0, k=(0, 0, 0), noise=None):
    details = {"noise": noise} if noise else {}
    return TriadCalibration(sensor, np.asarray(M, float), np.asarray(b0, float),
                            np.asarray(k, float), details=details)


def full_M(scale=1.0):
    """A general (non-symmetric, non-triangular) correction matrix near ``scale * I``."""
    return scale * (np.eye(3) + 0.01 * RNG.standard_normal((3, 3)))


def sym_M():
    A = 0.02 * RNG.standard_normal((3, 3))
    return np.eye(3) * 1.05 + (A + A.T) / 2


def context(frame="FRD", temperature=True, topic=None, device_id="1310988", units=None):
    facts = {s: {"rate_hz": 200.0, "frame_convention": frame, "device_id": device_id}
             for s in ("accel", "gyro", "mag")}
    if topic:
        facts["accel"]["topic"] = topic
    if temperature:
        facts["temperature"] = {"rate_hz": 200.0, "min_C": TEMPS[0], "max_C": TEMPS[1]}
    return {"session": "s.mcap", "imupipe_version": "test", "stream_facts": facts,
            "raw_units": units or {}, "device": "imu1"}


def export(exporter, triads, ctx, tmp_path, extra=None):
    results = {"cal": triads_to_table(list(triads)), **(extra or {})}
    paths = exporter.export(results, ctx, tmp_path)
    return {p.name: p.read_text() for p in paths}


def raw(n=50, scale=10.0):
    return scale * RNG.standard_normal((n, 3)), RNG.uniform(*TEMPS, n)


# --------------------------------------------------------------------------- imu_tk


def imutk_correct(text, y):
    """imu_tk CalibratedTriad_::load: 9 + 9 + 3 numbers; X' = T K (X - B)."""
    numbers = [float(v) for v in text.split("#", 1)[0].split()][:21]
    T, K, B = np.reshape(numbers[:9], (3, 3)), np.reshape(numbers[9:18], (3, 3)), numbers[18:]
    return (y - B) @ (T @ K).T


def test_imu_tk_round_trip_counts(tmp_path, caplog):
    acc = triad("accel", full_M(0.0024), [33000, 33200, 32400], k=[0.5, 0, -0.2])
    gyro = triad("gyro", full_M(2e-4), [32700, 32400, 32500])
    files = export(imu_tk.ImuTkExporter(), [acc, gyro], context(units={"accel": "counts",
                                                                       "gyro": "counts"}),
                   tmp_path)
    assert sorted(files) == ["imu_tk_acc.calib", "imu_tk_gyro.calib"]
    y, _ = raw(scale=3000.0)
    y += 32768
    close(imutk_correct(files["imu_tk_gyro.calib"], y), gyro.apply(y))
    close(imutk_correct(files["imu_tk_acc.calib"], y), acc.apply(y, 25.0))  # B is b0 at 25 degC
    # T has a unit diagonal, K is diagonal: imu_tk's own shape
    numbers = [float(v) for v in files["imu_tk_acc.calib"].split("#", 1)[0].split()]
    assert np.allclose(np.diag(np.reshape(numbers[:9], (3, 3))), 1.0)
    assert "k = [0.5, 0.0, -0.2]" in files["imu_tk_acc.calib"]
    assert "k = [0.5, 0.0, -0.2]" in caplog.text and "imu_tk export" in caplog.text


# --------------------------------------------------------------------------- imu_calib


def test_imu_calib_round_trip_with_frame_change(tmp_path, caplog):
    """Recorded in FRD (a ULog), applied by imu_calib to ROS FLU messages: y_flu = R y_frd."""
    acc = triad("accel", full_M(), [0.1, -0.2, 0.3])
    gyro = triad("gyro", np.eye(3), [0.01, 0, 0])
    files = export(imu_calib.ImuCalibExporter(), [acc, gyro], context("FRD"), tmp_path)
    doc = yaml.safe_load(files["imu_calib.yaml"])
    SM, bias = np.reshape(doc["SM"], (3, 3)), np.asarray(doc["bias"])
    y, _ = raw()
    corrected_flu = (y @ R.T) @ SM.T - bias  # AccelCalib::applyCalib: SM raw - bias
    close(corrected_flu, acc.apply(y) @ R.T)
    assert "R = diag(1, -1, -1)" in files["imu_calib.yaml"]
    assert "gyro calibration" in caplog.text


def test_imu_calib_refuses_counts(tmp_path):
    acc = triad("accel", full_M(0.0024), [33000, 33200, 32400])
    with pytest.raises(ExportError, match="accel in counts"):
        export(imu_calib.ImuCalibExporter(), [acc], context(units={"accel": "counts"}), tmp_path)


# --------------------------------------------------------------------------- PX4


def px4_params(text):
    rows = [line.split("\t") for line in text.splitlines() if line and not line.startswith("#")]
    assert all(len(r) == 5 and r[:2] == ["1", "1"] and r[4] in ("6", "9") for r in rows)
    return {r[2]: float(r[3]) for r in rows}


def px4_vec(p, fmt):
    return np.array([p[fmt.format(a)] for a in "XYZ"])


def px4_thermal(p, short, n, T):
    """calc_thermal_offsets_3D: cubic in dT = clamp(T, TMIN, TMAX) - TREF."""
    if p.get(f"TC_{short}_ENABLE") != 1:
        return 0.0
    Tc = np.clip(T, p[f"TC_{short}{n}_TMIN"], p[f"TC_{short}{n}_TMAX"]) - p[f"TC_{short}{n}_TREF"]
    c = [np.array([p[f"TC_{short}{n}_X{o}_{i}"] for i in range(3)]) for o in range(4)]
    return sum(np.multiply.outer(Tc**o, c[o]) for o in range(4))


def test_px4_round_trip(tmp_path, caplog):
    acc = triad("accel", np.diag([1.01, 0.99, 1.003]), [0.1, -0.2, 0.3], k=[1e-3, -2e-3, 5e-4])
    gyro = triad("gyro", np.eye(3), [0.01, -0.02, 0.005], k=[1e-4, 0, -1e-4])
    mag = triad("mag", sym_M(), [1e-6, -2e-6, 3e-7])
    files = export(px4.Px4Exporter(), [acc, gyro, mag], context("FRD"), tmp_path)
    text = files["px4.params"]
    assert text.startswith("# Onboard parameters for Vehicle 1\n")
    p = px4_params(text)
    assert p["CAL_ACC1_ID"] == p["TC_A1_ID"] == p["CAL_MAG1_ID"] == 1310988  # device imu1
    y, T = raw()
    # Accelerometer::Correct: (data - thermal - offset) .* scale
    got = (y - px4_thermal(p, "A", 1, T) - px4_vec(p, "CAL_ACC1_{}OFF")) * px4_vec(
        p, "CAL_ACC1_{}SCALE")
    close(got, acc.apply(y, T))
    got = y - px4_thermal(p, "G", 1, T) - px4_vec(p, "CAL_GYRO1_{}OFF")
    close(got, gyro.apply(y, T))
    # Magnetometer::Correct in gauss: S (data - offset)
    S = np.array([[p["CAL_MAG1_XSCALE"], p["CAL_MAG1_XODIAG"], p["CAL_MAG1_YODIAG"]],
                  [p["CAL_MAG1_XODIAG"], p["CAL_MAG1_YSCALE"], p["CAL_MAG1_ZODIAG"]],
                  [p["CAL_MAG1_YODIAG"], p["CAL_MAG1_ZODIAG"], p["CAL_MAG1_ZSCALE"]]])
    y_T = y * 1e-5
    got_gauss = (y_T * 1e4 - px4_vec(p, "CAL_MAG1_{}OFF")) @ S.T
    close(got_gauss * 1e-4, mag.apply(y_T))
    assert "NOT HELD" not in text and not caplog.records
    # outside the session's range PX4 holds the offset: said in the file
    assert f"{TEMPS[0]:.2f} to {TEMPS[1]:.2f} degC" in text


def test_px4_from_flu_and_what_it_cannot_hold(tmp_path, caplog):
    """A ROS recording (FLU) to PX4 (FRD): M' = R M R; cross-axis, gyro M and the mag
    rotation are dropped, said in the file and the log."""
    acc = triad("accel", full_M(), [0.1, -0.2, 0.3])
    gyro = triad("gyro", full_M(), [0.01, -0.02, 0.005])
    mag = triad("mag", full_M(), [1e-6, -2e-6, 3e-7])
    with caplog.at_level(logging.WARNING):
        text = export(px4.Px4Exporter(), [acc, gyro, mag], context("FLU", device_id=None),
                      tmp_path)["px4.params"]
    p = px4_params(text)
    y, _ = raw()
    y_frd = y @ R.T
    expected = acc.apply(y) @ R.T
    got = (y_frd - px4_vec(p, "CAL_ACC1_{}OFF")) * px4_vec(p, "CAL_ACC1_{}SCALE")
    # only the diagonal is held: the rest is the cross-axis part, of the size the note gives
    diag_only = (y_frd - R @ acc.b0) @ np.diag(np.diag(R @ acc.M @ R))
    close(got, diag_only)
    assert np.abs(got - expected).max() > 1e-3
    for said in ("accel cross-axis terms", "PX4 has no gyroscope scale",
                 "rotation part U of M = U P", "written as 0"):
        assert said in text and said in caplog.text
    assert p["CAL_ACC1_ID"] == 0


def test_px4_refuses_counts(tmp_path):
    acc = triad("accel", full_M(0.0024), [33000, 33200, 32400])
    with pytest.raises(ExportError, match="cannot export to PX4: raw values are accel in counts"):
        export(px4.Px4Exporter(), [acc], context(units={"accel": "counts"}), tmp_path)


# --------------------------------------------------------------------------- ArduPilot


def ap_params(text):
    rows = [line.split(",") for line in text.splitlines() if line and not line.startswith("#")]
    return {name: float(value) for name, value in rows}


def test_ardupilot_round_trip(tmp_path, caplog):
    acc = triad("accel", np.diag([1.01, 0.99, 1.003]), [0.1, -0.2, 0.3])
    gyro = triad("gyro", np.eye(3), [0.01, -0.02, 0.005], k=[1e-4, 0, 0])
    mag = triad("mag", sym_M(), [1e-6, -2e-6, 3e-7])
    text = export(ardupilot.ArduPilotExporter(), [acc, gyro, mag], context("FRD"),
                  tmp_path)["ardupilot.param"]
    p = ap_params(text)
    y, _ = raw()
    v = lambda fmt: np.array([p[fmt.format(a)] for a in "XYZ"])
    # device imu1 -> the second instance: INS_ACC2*, INS_GYR2*, COMPASS_*2
    close((y - v("INS_ACC2OFFS_{}")) * v("INS_ACC2SCAL_{}"), acc.apply(y))
    close(y - v("INS_GYR2OFFS_{}"), gyro.apply(y, 25.0))
    D = np.array([[p["COMPASS_DIA2_X"], p["COMPASS_ODI2_X"], p["COMPASS_ODI2_Y"]],
                  [p["COMPASS_ODI2_X"], p["COMPASS_DIA2_Y"], p["COMPASS_ODI2_Z"]],
                  [p["COMPASS_ODI2_Y"], p["COMPASS_ODI2_Z"], p["COMPASS_DIA2_Z"]]])
    y_T = y * 1e-5
    got_mG = (y_T * 1e7 + v("COMPASS_OFS2_{}")) @ D.T  # correct_field adds its offsets
    close(got_mG * 1e-7, mag.apply(y_T))
    assert "INS_TCAL polynomials are not written" in text and "k = [0.0001" in caplog.text


def test_ardupilot_parameter_names_of_the_first_instance():
    assert ardupilot.names("accel", 0) == {"offset": "INS_ACCOFFS_{axis}",
                                           "scale": "INS_ACCSCAL_{axis}"}
    assert ardupilot.names("gyro", 0) == {"offset": "INS_GYROFFS_{axis}"}
    assert ardupilot.names("gyro", 2) == {"offset": "INS_GYR3OFFS_{axis}"}
    assert ardupilot.names("mag", 0)["offset"] == "COMPASS_OFS_{axis}"


# --------------------------------------------------------------------------- Kalibr


def test_kalibr_noise_units_and_intrinsics(tmp_path, caplog):
    white = [0.02, 0.03, 0.025]  # per sample, raw units (SI here)
    acc = triad("accel", full_M(), [0.1, -0.2, 0.3], noise={"white_sigma": white})
    gyro = triad("gyro", full_M(), [0.01, 0.0, 0.0],
                 noise={"white_sigma": [1e-3] * 3, "bias_random_walk": [2e-5, 3e-5, 1e-5]})
    text = export(kalibr.KalibrExporter(), [acc, gyro], context(topic="/imu0/imu"),
                  tmp_path)["kalibr_imu.yaml"]
    doc = yaml.safe_load(text)
    # sigma_c = sigma_d / sqrt(rate), through M, largest axis
    per_axis = np.sqrt((acc.M**2) @ (np.array(white) ** 2)) / np.sqrt(200.0)
    assert doc["accelerometer_noise_density"] == pytest.approx(per_axis.max(), rel=1e-12)
    walk = np.sqrt((gyro.M**2) @ np.array([2e-5, 3e-5, 1e-5]) ** 2)
    assert doc["gyroscope_random_walk"] == pytest.approx(walk.max(), rel=1e-12)
    assert doc["accelerometer_random_walk"] is None and "accelerometer_random_walk" in caplog.text
    assert doc["rostopic"] == "/imu0/imu" and doc["update_rate"] == 200.0
    # intrinsics: measured = M_a a_i + b, a_i = C_i_imupipe x; gyro: M_g C_gyro_i w_i + b
    Ma = np.array(doc["accelerometers"]["M"])
    Mg, C = np.array(doc["gyroscopes"]["M"]), np.array(doc["gyroscopes"]["C_gyro_i"])
    Q = np.array(doc["imupipe"]["C_i_imupipe"])
    assert np.allclose(np.triu(Ma, 1), 0) and np.allclose(np.triu(Mg, 1), 0)
    for rot in (Q, C):
        close(rot @ rot.T, np.eye(3))
        assert np.linalg.det(rot) == pytest.approx(1.0)
    y, _ = raw()
    a_i = (y - acc.b0) @ np.linalg.inv(Ma).T
    close(a_i, acc.apply(y) @ Q.T)
    w_i = (y - gyro.b0) @ np.linalg.inv(Mg @ C).T
    close(w_i, gyro.apply(y) @ Q.T)


def test_kalibr_prefers_a_noise_table(tmp_path):
    acc = triad("accel", np.eye(3) * 2, [0, 0, 0], noise={"white_sigma": [1.0] * 3})
    gyro = triad("gyro", np.eye(3), [0, 0, 0])
    rows = [{"sensor": s, "axis": a, "noise_density": d, "random_walk": w, "rate_hz": 200.0}
            for s, d, w in (("accel", 1e-3, 1e-4), ("gyro", 2e-4, 3e-6)) for a in "xyz"]
    noise = pa.table({k: [r[k] for r in rows] for k in rows[0]})
    noise = noise.replace_schema_metadata({schemas.SCHEMA_KEY: b"noise"})
    doc = yaml.safe_load(export(kalibr.KalibrExporter(), [acc, gyro], context(), tmp_path,
                                {"noise.noise": noise})["kalibr_imu.yaml"])
    assert doc["accelerometer_noise_density"] == pytest.approx(2e-3)  # through M = 2 I
    assert doc["accelerometer_random_walk"] == pytest.approx(2e-4)
    assert doc["gyroscope_noise_density"] == pytest.approx(2e-4)
    assert doc["gyroscope_random_walk"] == pytest.approx(3e-6)


def test_every_written_file_says_its_source_and_conventions(tmp_path):
    acc = triad("accel", np.eye(3), [0, 0, 0])
    for exporter in (imu_tk.ImuTkExporter(), imu_calib.ImuCalibExporter(),
                     px4.Px4Exporter(), ardupilot.ArduPilotExporter(), kalibr.KalibrExporter()):
        for name, text in export(exporter, [acc], context(), tmp_path / exporter.name).items():
            assert name in exporter.files
            assert re.search(r"written by imupipe test for ", text)
            assert "x = M (y - b0 - k (T - 25 degC))" in text and "Conversions:" in text

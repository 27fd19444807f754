"""The verdict of a calibration: pass, warn or fail, with one line per reason.

``judge`` runs the checks a metrologist makes before trusting a calibration,
on what a run produced (the ``calibration.json`` document, the report tables
recognised by schema, the streams' facts) and returns
``{"status": "pass|warn|fail", "reasons": [...], "checks": [...]}``
(``spec/contracts.md``; ``checks`` lists every check made, reasons only the
warn and fail ones). A check whose input the run did not produce is not made.

The checks and their limits (consumer-to-tactical MEMS, SI raw units):

- fit consistency: chi2/dof of every block of the joint fit and of the residual
  map against its expected spread, 1 +- sqrt(2/dof): warn beyond 5 sd when also
  above ``CHI2_WARN`` (residuals 1.4x the noise the fit assumed: the uncertainties
  are understated), fail above ``CHI2_FAIL`` (residuals 100x the noise: the model
  does not describe the data at all, e.g. swapped axes);
- validation: the turn-angle errors (``validate_turns``) against their
  tolerance, the control-set errors (``validate_control``) against the raw ones;
  a calibration that makes them worse than no calibration fails;
- plausible values: det M > 0 (a left-handed M is a sign or axis mix-up: fail), the
  gyro's axes within ``FRAME_WARN_DEG`` / ``FRAME_FAIL_DEG`` of the accelerometer's,
  the singular values of M within ``SCALE_RANGE`` of nominal, biases below
  ``BIAS_WARN`` / ``BIAS_FAIL``;
- uncertainties: reported, finite, and the 1-sigma of scale and bias below
  ``SIGMA_WARN``;
- coverage: a rest within ``COVERAGE_DEG`` of each of the six axis directions;
- drift without temperature: in a session without a temperature stream, the rests' calibrated
  gravity magnitude must not change with time beyond what a static calibration explains (an
  F-test of time-scaled scale and bias terms against the static ones, p below ``DRIFT_P``, and
  a drift over ``DRIFT_WARN_PPM`` of g: a thermal drift the calibration averages over);
- the streams: rate at least ``RATE_WARN_HZ`` (``RATE_FAIL_HZ``), and the events
  the screening found (``EVENT_STATUS``: a splice fails, as its sections may come from
  different power-ups; gaps and shocks warn, the turns holding them being left out).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from . import schemas, tails
from .columns import vectors
from .models import UNITS

CHI2_SD = 5.0  # beyond this many standard deviations of its spread, chi2/dof is not noise
CHI2_WARN = 2.0
CHI2_FAIL = 1e4  # residuals 100 times the noise: swapped axes, wrong units (real recordings with
# unmodelled physics reach 10-1000: a warning that the uncertainties are understated)
SCALE_RANGE = (0.8, 1.25)  # singular values of M (accel, gyro) for raw SI data
MAG_FIELD_T = (2e-6, 5e-4)  # the calibrated field magnitude (Earth: 25-65 uT; disturbed up to 500)
MAG_ANISOTROPY_WARN = 2.0  # ratio of the largest to the smallest singular value of the mag M
BIAS_WARN = {"accel": 1.5, "gyro": 0.35}  # m/s^2 (~150 mg), rad/s (20 deg/s)
BIAS_FAIL = {"accel": 3.0, "gyro": 1.75}  # ~300 mg, 100 deg/s
SIGMA_WARN = {"scale": 0.01, "accel": 0.05, "gyro": 0.005}  # 1 %, ~5 mg, ~0.3 deg/s
FRAME_WARN_DEG = 5.0  # gyro vs accelerometer axes (one IMU: a degree or two at most)
FRAME_FAIL_DEG = 30.0
COVERAGE_DEG = 60.0
DRIFT_P = 1e-6  # the time terms explain the rests' gravity magnitude beyond chance
DRIFT_WARN_PPM = 1000.0  # and move it by more than 0.1 % of g over the session
DRIFT_MIN_RESTS = 24  # 9 static + 6 time terms need enough rests to test
RATE_WARN_HZ = 50.0
RATE_FAIL_HZ = 10.0
VALIDATION_ACCEPTED_WARN = 0.9  # fraction of informative turns within tolerance
VALIDATION_ACCEPTED_FAIL = 0.5  # with at least VALIDATION_MIN_TURNS informative turns
VALIDATION_MIN_TURNS = 5
EVENT_STATUS = {"splice": "fail", "gap": "warn", "shock": "warn", "saturation": "warn"}
PRINTED_REASONS = 6  # under each path ``imupipe run`` prints; all are in calibration.json
NO_MAP = ("every sample against the calibrated model: this pipeline has no residual map (the checks judge "
          "the joint fit's rests and turns; the default pipeline has the map)")
ORDER = {"pass": 0, "warn": 1, "fail": 2}
STATUSES = tuple(ORDER)


@dataclass(frozen=True)
class Check:
    """One check: ``name`` (what was checked), ``status`` pass|warn|fail, ``detail`` one line."""

    name: str
    status: str
    detail: str

    def to_dict(self) -> dict[str, str]:
        return {"check": self.name, "status": self.status, "detail": self.detail}


def judge(calibration: Mapping[str, Any], tables: Mapping[str, pa.Table] | None = None,
          facts: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """The verdict of ``calibration`` (a ``calibration.json`` document, ``raw_units`` per triad
    included) given the run's report ``tables`` (any names; recognised by schema) and the
    streams' ``facts`` (``ingest.stream_facts``: ``rate_hz`` per stream)."""
    by_schema: dict[str, list[pa.Table]] = {}
    for t in (tables or {}).values():
        if t is not None:
            by_schema.setdefault(schemas.schema_of(t) or "", []).append(t)
    checks: list[Check] = []
    maps = [_map_doc(t) for t in by_schema.get("residual_map", [])]
    checks += fit_checks(calibration, maps)
    checks += validation_checks(by_schema.get("validation", []), by_schema.get("control_errors", []))
    checks += value_checks(calibration)
    checks += frame_checks(calibration)
    checks += sigma_checks(calibration)
    checks += coverage_checks(by_schema.get("rests", []), calibration.get("accel"))
    checks += drift_checks(by_schema.get("rests", []), calibration.get("accel"))
    checks += stream_checks(facts or {}, by_schema.get("events", []))
    verdict = summarise(checks)
    if _joint_fit(calibration) is not None and not maps:  # calibrate.toml: said, not a warning
        verdict["not_checked"] = [NO_MAP]
    return verdict


def summarise(checks: list[Check]) -> dict[str, Any]:
    status = max((c.status for c in checks), key=ORDER.__getitem__, default="pass")
    ranked = sorted((c for c in checks if c.status != "pass"), key=lambda c: -ORDER[c.status])
    return {"status": status, "reasons": [f"{c.status}: {c.detail}" for c in ranked],
            "checks": [c.to_dict() for c in checks]}


def _map_doc(table: pa.Table) -> dict:
    raw = (table.schema.metadata or {}).get(b"imupipe.residual_map")
    return json.loads(raw) if raw else {}


# --------------------------------------------------------------------------- fit consistency


def chi2_status(chi2_per_dof: float, dof: float) -> str:
    """pass | warn | fail for one block's chi2/dof of ``dof`` degrees of freedom."""
    if not np.isfinite(chi2_per_dof):
        return "fail"
    if chi2_per_dof > CHI2_FAIL:
        return "fail"
    z = (chi2_per_dof - 1.0) / np.sqrt(2.0 / max(dof, 1e-9))
    if z > CHI2_SD and chi2_per_dof > CHI2_WARN:
        return "warn"
    if z < -CHI2_SD:
        return "warn"
    return "pass"


def _joint_fit(calibration: Mapping[str, Any]) -> Mapping[str, Any] | None:
    """The joint fit's details (both triads carry the same), None without one."""
    for sensor in ("accel", "gyro"):
        joint = (calibration.get(sensor) or {}).get("joint")
        if isinstance(joint, Mapping):
            return joint
    return None


def fit_checks(calibration: Mapping[str, Any], maps: list[dict]) -> list[Check]:
    blocks: list[tuple[str, float, float]] = []
    joint = _joint_fit(calibration) or {}
    for name, b in (joint.get("blocks") or {}).items():
        if b.get("chi2_per_dof") is not None and b.get("dof"):
            blocks.append((f"joint fit {name}", float(b["chi2_per_dof"]), float(b["dof"])))
    saturated = int(joint.get("turns_saturated") or 0)
    for doc in maps:
        for b in doc.get("blocks", []):
            if b.get("chi2_per_dof") is not None and b.get("dof"):
                name = b.get("block") or f"{b.get('sensor')} {b.get('kind')}"
                blocks.append((f"residual map {name}", float(b["chi2_per_dof"]), float(b["dof"])))
    out = []
    # a pipeline without the map (calibrate.toml) must not send the reader to it
    see = "see the residual map" if maps else "the default pipeline's residual map shows where"
    for name, c, dof in blocks:
        status = chi2_status(c, dof)
        spread = np.sqrt(2.0 / dof)
        what = {"pass": "within its spread",
                "warn": f"beyond its expected spread: residuals {np.sqrt(c):.2g}x the noise the fit "
                        f"assumed, its uncertainties understated (unmodelled physics? {see})",
                "fail": "far beyond the noise: the model does not describe the recording "
                        f"(swapped or sign-flipped axes? wrong units? {see})"}[status]
        if status == "warn" and c < 1:
            what = "below its expected spread: the noise model overstates the noise"
        out.append(Check("chi2", status, f"{name}: chi2/dof {c:.3g} over {dof:.0f} dof "
                                         f"(expected 1 +- {spread:.2g}): {what}"))
    if saturated:
        out.append(Check("events", "warn", f"{saturated} turns left out of the joint fit: their gyro "
                         "samples reach the saturation rate (turn slower)"))
    return out


# --------------------------------------------------------------------------- validation


def _summary(table: pa.Table) -> dict:
    return json.loads((table.schema.metadata or {}).get(b"imupipe.summary", b"{}"))


def validation_checks(validations: list[pa.Table], controls: list[pa.Table]) -> list[Check]:
    out = []
    for t in validations:
        s = _summary(t)
        n_inf, n_ok = int(s.get("n_informative", 0)), int(s.get("n_accepted", 0))
        tol = float(s.get("tolerance_deg", float("nan")))
        before = float(s.get("angle_error_rms_before_deg", float("nan")))
        after = float(s.get("angle_error_rms_after_deg", float("nan")))
        if n_inf == 0:
            out.append(Check("validation", "warn", f"turn validation: none of {s.get('n_turns', 0)} "
                             "turns tilts gravity enough to validate the gyro (record turns about "
                             "horizontal axes)"))
            continue
        frac = n_ok / n_inf
        detail = (f"turn validation: {n_ok} of {n_inf} turns within {tol:g} deg, angle error RMS "
                  f"{after:.3g} deg after calibration ({before:.3g} deg before)")
        if not np.isfinite(after) or (np.isfinite(before) and after > before):
            status, detail = "fail", detail + ": the calibration makes the turns worse"
        elif frac < VALIDATION_ACCEPTED_FAIL and n_inf >= VALIDATION_MIN_TURNS:
            status = "fail"
        elif frac < VALIDATION_ACCEPTED_WARN or after > tol:
            status = "warn"
        else:
            status = "pass"
        out.append(Check("validation", status, detail))
    for t in controls:
        after = _col(t, "error_after_deg")
        before = _col(t, "error_before_deg")
        if not len(after):
            continue
        r_after, r_before = _rms(after), _rms(before)
        detail = (f"control set: gravity carried through {len(after)} turns misses by {r_after:.3g} deg "
                  f"RMS after calibration ({r_before:.3g} deg before)")
        status = "pass"
        if not np.isfinite(r_after) or r_after >= r_before:
            status, detail = "fail", detail + ": the calibration does not improve them"
        out.append(Check("control", status, detail))
    return out


def _col(t: pa.Table, name: str) -> np.ndarray:
    if name not in t.column_names:
        return np.zeros(0)
    return np.asarray(t.column(name).to_numpy(zero_copy_only=False), float)


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if len(x) else float("nan")


# --------------------------------------------------------------------------- plausible values


def _is_si(calibration: Mapping[str, Any], sensor: str) -> bool:
    return calibration[sensor].get("raw_units", UNITS[sensor]) == UNITS[sensor]


def value_checks(calibration: Mapping[str, Any]) -> list[Check]:
    out = []
    for sensor in ("accel", "gyro", "mag"):
        if sensor not in calibration:
            continue
        M = np.asarray(calibration[sensor]["M"], float)
        b0 = np.asarray(calibration[sensor].get("b0", [0, 0, 0]), float)
        if not (np.isfinite(M).all() and np.isfinite(b0).all()):
            out.append(Check("values", "fail", f"{sensor}: M or b0 is not finite"))
            continue
        det = float(np.linalg.det(M))
        if det <= 0:
            out.append(Check("values", "fail", f"{sensor}: det M = {det:.3g} <= 0, a left-handed "
                             "calibration (an axis sign-flipped or two axes swapped in the data or "
                             "the reader's columns): fix the axis mapping and rerun"))
        sv = np.linalg.svd(M, compute_uv=False)
        si = _is_si(calibration, sensor)
        if sensor == "mag":
            field = calibration[sensor].get("field_T")
            if si and isinstance(field, (int, float)):
                lo, hi = MAG_FIELD_T
                bad = not lo <= field <= hi
                out.append(Check("values", "fail" if bad else "pass",
                                 f"mag: field {field:.3g} T (an Earth field is {lo:g} to {hi:g} T)"
                                 + (": the raw data are not in tesla (uT? gauss?); give the unit in "
                                    "a session manifest" if bad else "")))
            ratio = float(sv[0] / sv[-1])
            out.append(Check("values", "warn" if ratio > MAG_ANISOTROPY_WARN else "pass",
                             f"mag: soft-iron anisotropy {ratio:.3g} (largest / smallest singular "
                             f"value of M; above {MAG_ANISOTROPY_WARN:g} is implausible)"))
            continue
        if si:
            lo, hi = SCALE_RANGE
            bad = (sv < lo) | (sv > hi)
            out.append(Check("values", "fail" if bad.any() else "pass",
                             f"{sensor}: scale factors {', '.join(f'{1 / s:.4g}' for s in sv[::-1])} x "
                             f"nominal (plausible {1 / hi:.3g} to {1 / lo:.3g})"
                             + (": wrong units or a failed fit" if bad.any() else "")))
            worst = float(np.abs(b0).max())
            unit = UNITS[sensor]
            status = "fail" if worst > BIAS_FAIL[sensor] else "warn" if worst > BIAS_WARN[sensor] else "pass"
            out.append(Check("values", status, f"{sensor}: largest bias {worst:.3g} {unit} (warn above "
                             f"{BIAS_WARN[sensor]:g}, fail above {BIAS_FAIL[sensor]:g} {unit})"))
    return out


def _rotation_part(M: np.ndarray) -> np.ndarray:
    """The rotation Q of the polar decomposition M = Q H (H symmetric positive definite)."""
    U, _, Vt = np.linalg.svd(M)
    Q = U @ Vt
    return Q


def frame_checks(calibration: Mapping[str, Any]) -> list[Check]:
    """The gyro's axes against the accelerometer's: sensors of one IMU are aligned within a
    few degrees; a half turn is an axis sign-flipped in the accelerometer (the gyro then
    absorbs it as a proper rotation, and det M stays positive)."""
    if "accel" not in calibration or "gyro" not in calibration:
        return []
    Ma, Mg = (np.asarray(calibration[s]["M"], float) for s in ("accel", "gyro"))
    if not (np.isfinite(Ma).all() and np.isfinite(Mg).all()) or np.linalg.det(Ma) * np.linalg.det(Mg) <= 0:
        return []  # the det check has said it
    R = _rotation_part(Mg) @ _rotation_part(Ma).T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    status = "fail" if angle > FRAME_FAIL_DEG else "warn" if angle > FRAME_WARN_DEG else "pass"
    detail = f"gyro axes turned {angle:.3g} deg from the accelerometer's (warn above {FRAME_WARN_DEG:g})"
    if status == "fail":
        detail += (": an axis sign-flipped or two axes swapped in one triad (the calibrated frame "
                   "is left-handed or mislabelled): fix the axis mapping and rerun")
    return [Check("frames", status, detail)]


def sigma_checks(calibration: Mapping[str, Any]) -> list[Check]:
    out = []
    for sensor in ("accel", "gyro"):
        tri = calibration.get(sensor)
        if not tri:
            continue
        sM, sb = tri.get("sigma_M"), tri.get("sigma_b0")
        if sM is None or sb is None:
            out.append(Check("uncertainty", "pass", f"{sensor}: no uncertainties reported by "
                             f"{tri.get('solver') or 'the solver'}"))
            continue
        sM, sb = np.asarray(sM, float), np.asarray(sb, float)
        if not (np.isfinite(sM).all() and np.isfinite(sb).all()):
            out.append(Check("uncertainty", "warn", f"{sensor}: uncertainties are not finite "
                             "(a parameter the recording does not determine)"))
            continue
        M = np.abs(np.diag(np.asarray(tri["M"], float)))
        rel = float((np.diag(sM) / np.where(M > 0, M, 1)).max())
        sbm = float(sb.max())
        unit = tri.get("raw_units", UNITS[sensor])
        gauge = ((tri.get("joint") or {}).get("gauge") or "").split(":")[0]
        warn = rel > SIGMA_WARN["scale"] or (unit == UNITS[sensor] and sbm > SIGMA_WARN[sensor])
        out.append(Check("uncertainty", "warn" if warn else "pass",
                         f"{sensor}: 1-sigma scale {rel * 1e6:.3g} ppm, bias {sbm:.3g} {unit}"
                         + (f" (gauge: {gauge})" if gauge else "")
                         + (" : too uncertain to trust; record more positions or longer rests" if warn else "")))
    return out


# --------------------------------------------------------------------------- coverage, streams

AXES = ("+x", "-x", "+y", "-y", "+z", "-z")


def coverage_checks(rests_tables: list[pa.Table], accel: Mapping[str, Any] | None = None) -> list[Check]:
    """Calibrated gravity directions of the rests (raw ones without an accel calibration)."""
    out = []
    for t in rests_tables[:1]:
        if "accel_mean" not in t.column_names or t.num_rows == 0:
            continue
        a = vectors(t, "accel_mean").astype(float)
        a = a[np.isfinite(a).all(axis=1)]
        if accel is not None:
            a = (a - np.asarray(accel.get("b0", [0, 0, 0]), float)) @ np.asarray(accel["M"], float).T
        u = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-300)
        dirs = np.vstack([np.eye(3), -np.eye(3)])[[0, 3, 1, 4, 2, 5]]
        nearest = np.degrees(np.arccos(np.clip((u @ dirs.T).max(axis=0), -1, 1)))
        worst = int(np.argmax(nearest))
        status = "warn" if nearest[worst] > COVERAGE_DEG else "pass"
        out.append(Check("coverage", status, f"rests: {len(u)}; gravity comes within {nearest[worst]:.0f} deg "
                         f"of sensor {AXES[worst]} at best (the worst of the six axis directions; "
                         f"warn beyond {COVERAGE_DEG:g})"
                         + (": record positions around it" if status == "warn" else "")))
    return out


def drift_checks(rests_tables: list[pa.Table], accel: Mapping[str, Any] | None) -> list[Check]:
    """A session without temperature whose accelerometer drifts (thermally): the calibrated
    gravity magnitude of its rests changes with time in a way no static calibration explains.

    The magnitude residual of rest i, |M (a_i - b0)| - g, is regressed on the static terms a
    re-fit could still absorb (1, u^2, u_j u_k, u: u the rest's gravity direction) and then
    also on the same scale and bias terms times the rest's time (t u^2, t u). The F-test of the
    time terms and the range of their fitted drift over the session decide; the test uses the
    residuals' own scatter, not an assumed noise."""
    if accel is None:
        return []
    out = []
    for t in rests_tables[:1]:
        need = {"accel_mean", "t_start_s", "t_end_s"}
        if not need <= set(t.column_names) or t.num_rows < DRIFT_MIN_RESTS:
            continue
        if "temperature" in t.column_names and np.isfinite(_col(t, "temperature")).any():
            continue  # the thermal stage models it (k); this check is for sessions without
        a = vectors(t, "accel_mean").astype(float)
        mid = 0.5 * (_col(t, "t_start_s") + _col(t, "t_end_s"))
        ok = np.isfinite(a).all(axis=1) & np.isfinite(mid)
        a, mid = a[ok], mid[ok]
        M, b0 = np.asarray(accel["M"], float), np.asarray(accel.get("b0", [0, 0, 0]), float)
        if len(a) < DRIFT_MIN_RESTS or not (np.isfinite(M).all() and np.isfinite(b0).all()):
            continue
        c = (a - b0) @ M.T
        norm = np.linalg.norm(c, axis=1)
        if not (norm > 0).all() or np.ptp(mid) <= 0:
            continue
        u, g = c / norm[:, None], float(np.median(norm))
        r = norm - g
        tau = (mid - mid.mean()) / np.ptp(mid)
        static = np.column_stack([np.ones(len(u)), u[:, :2] ** 2, u[:, [0, 0, 1]] * u[:, [1, 2, 2]], u])
        timed = tau[:, None] * np.column_stack([u**2, u])
        X = np.column_stack([static, timed])
        rss0 = _rss(static, r)[0]
        rss1, beta = _rss(X, r)
        dof = len(r) - X.shape[1]
        if dof < 8 or rss1 <= 0:
            continue
        F = (rss0 - rss1) / timed.shape[1] / (rss1 / dof)
        p = tails.f_sf(F, timed.shape[1], dof)
        drift = timed @ beta[static.shape[1]:]
        ppm = 1e6 * float(np.ptp(drift)) / g
        warn = p < DRIFT_P and ppm > DRIFT_WARN_PPM
        detail = (f"accel drift without a temperature stream: time-dependent scale and bias terms "
                  f"move the rests' calibrated gravity magnitude by {ppm:.3g} ppm over "
                  f"{np.ptp(mid):.0f} s (F-test p = {p:.2g}; warn above {DRIFT_WARN_PPM:g} ppm at "
                  f"p < {DRIFT_P:g})")
        if warn:
            detail += (": a drift no static calibration explains (thermal warm-up?); the scale and "
                       "bias are averages over it, off by up to that much; log the IMU's "
                       "temperature, or record after the warm-up")
        out.append(Check("drift", "warn" if warn else "pass", detail))
    return out


def _rss(X: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(((y - X @ beta) ** 2).sum()), beta


def stream_checks(facts: Mapping[str, Mapping[str, Any]], events: list[pa.Table]) -> list[Check]:
    out = []
    for sensor in ("accel", "gyro"):
        rate = (facts.get(sensor) or {}).get("rate_hz")
        if rate is None:
            continue
        status = "fail" if rate < RATE_FAIL_HZ else "warn" if rate < RATE_WARN_HZ else "pass"
        out.append(Check("rate", status, f"{sensor}: {rate:.4g} Hz (warn below {RATE_WARN_HZ:g} Hz: "
                         "turns are integrated too coarsely)" if status != "pass" else f"{sensor}: {rate:.4g} Hz"))
    for t in events:
        kinds = [str(k) for k in t.column("kind").to_pylist()] if "kind" in t.column_names else []
        if not kinds:
            out.append(Check("events", "pass", "no gaps, shocks or splices found"))
            continue
        meta = t.schema.metadata or {}
        left, total = meta.get(b"imupipe.turns_left_out"), meta.get(b"imupipe.turns")
        details = t.column("detail").to_pylist() if "detail" in t.column_names else []
        for kind in dict.fromkeys(kinds):
            n = kinds.count(kind)
            first = details[kinds.index(kind)] if details else ""
            detail = f"{n} {kind}{'s' if n > 1 else ''} in the recording; first: {first}"
            if kind == "splice":
                detail += ("; the sections may differ in turn-on bias and temperature: split the "
                           "recording at the splices and calibrate each section, or record one session")
            out.append(Check("events", EVENT_STATUS.get(kind, "warn"), detail))
        if left is not None and int(left):
            out.append(Check("events", "warn", f"{int(left)} of {int(total or 0)} turns left out of the "
                             "fits: they hold a gap, shock or splice"))
    return out


def read_verdict(calibration_json) -> dict | None:
    """The ``verdict`` of a written ``calibration.json`` (None when it has none)."""
    from pathlib import Path

    try:
        return json.loads(Path(calibration_json).read_text()).get("verdict")
    except (OSError, ValueError):
        return None


def verdict_lines(verdict: Mapping[str, Any] | None) -> list[str]:
    """What ``imupipe run`` prints under each calibration: the status, then one line per reason."""
    if not verdict:
        return ["verdict: none (the calibration was not judged)"]
    reasons = list(verdict.get("reasons", []))
    n = len(verdict.get("checks", []))
    head = f"verdict: {verdict.get('status', '?')}"
    head += f" ({n} checks)" if not reasons else f" ({len(reasons)} of {n} checks)"
    more = [f"  ... {len(reasons) - PRINTED_REASONS} more in calibration.json and report.md"] \
        if len(reasons) > PRINTED_REASONS else []
    return [head, *(f"  {r}" for r in reasons[:PRINTED_REASONS]), *more]


def strict_failure(verdicts: list[Mapping[str, Any] | None]) -> bool:
    """``--strict``: True when any verdict is warn or fail (or missing)."""
    return any(not v or v.get("status") != "pass" for v in verdicts)


__all__ = ["Check", "chi2_status", "judge", "read_verdict", "strict_failure", "summarise", "verdict_lines"]

"""Name the physics a calibrated model leaves out, fit it, and check it on data it did not fit.

Each catalogue effect that offers ``regressors`` becomes a candidate: its term's whitened
columns ``C`` on the rows of the fitted per-sample model (``evaluate``): accelerometer
rest means and motion samples, gyro rest means, and (for a gyro term) every row the motions'
gyro samples reach through the integrated attitude. Everything the nominal model can already
do is projected off (``Cp = (I - P) C`` with ``P`` the projector on the calibration's and
the nuisances' Jacobian, through the fit's own block-tridiagonal system), so

- the **visible fraction** ``|Cv| / |C|`` (the memo's ``|P_perp z| / |z|``, smallest over the
  term's directions; ``Cv`` projected with the bias walks held still, ``rigid_walks``) says
  whether this recording can tell the effect from the nominal parameters at all; below
  ``VISIBLE_MIN`` it goes to ``not_identifiable`` with the parameters it would bias. What the
  walks can mimic on top is a loss of power, counted in the information and the minimum
  detectable size (from ``Cp``, the walks free under their prior), not a concealment;
- the **score statistic** ``r' Cp (Cp' Cp)^-1 Cp' r`` is chi-square with the term's
  dimension under the null (scaled by the affected rows' chi2/dof when that exceeds 1,
  so an under-modelled noise floor does not pass for physics);
- **forward selection**: at each step every remaining candidate is tested conditionally on
  those accepted, Benjamini-Hochberg at ``q`` over them, the strongest significant one is
  accepted (its term refitted jointly with the others by the linearised Gauss-Newton step),
  then a backward check drops any accepted term that lost significance;
- **held-out proof**: by blocked cross-validation (for a static or warm-up term, 20
  contiguous stretches of time, whole rests and whole motions, each held out in turn) the
  calibration, every nuisance and the term are refitted without a stretch (one linearised
  step) and its residual RMS in the sensor's units is compared without and with the term.
  Refitting the nuisances matters: a bias walk already fitted to the rows it is judged on
  copies any slow term there. The proof is the z-score of the predictive chi2's decrease
  summed over the stretches (``_predictive_chi2``: what a stretch adds to the fit's chi2,
  without the term less with it), which judges each prediction by its own uncertainty (a
  walk bridging a held-out stretch is uncertain there; its squared error alone would
  drown the term), against its standard error (``_gain_z``). A motion term is held out by
  single rests and motions, leave-one-out in closed form (``_leave_one_out``).

A p-value is the larger of the asymptotic (chi-square) one and a wild bootstrap's over 5-s
time blocks (``wild_p``: the recording's own noise, whatever its colour, without a noise
model); ``bench/diagnosis.py`` measures how often nulls produce a finding. Where the residual
map finds a sensor's noise floor misfit (its ``all`` cell flagged: flicker noise, a bias that
wanders unlike a walk), that sensor's noise is correlated beyond 5 s and the model does not say
how far: its candidates' blocks are ``LONG_BLOCKS`` equal spans of the recording instead
(``time_blocks(lin, long=True)``; measured: on a gimbal null with flicker noise, an
accelerometer nonlinearity had p 0.001 over 5-s blocks and 0.007 over 120-s ones).

The gyro's scale terms (temperature, asymmetry) act on the rate it senses, so only inside
motions, through the attitude: most of their evidence is the attitude path's rows, and they are
held out by whole motions with those rows, judged whitened. The thermal lag is one ``tau`` for
both triads along their ``k``, from the slope of a spline through the de-quantised read-out;
a fitted lag below the temperature smoother's scale is the read-out's quantisation
(``rejects``: not confirmed). Saturation is not a term: clipped samples are events
(``events.clipped``) and their motions are left out. The magnetometer's effects are not tested
here yet: ``UNTESTED`` lists them with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from numpy.lib.stride_tricks import sliding_window_view

from .. import tails
from ..effects.earth_rotation import EARTH_RATE
from ..errors import SolverError
from ..models import T_REF_C
from ..solvers.blocktri import Bordered
from ..temperature import SMOOTH_S, rate_curve, temperature_rate
from .attitude import by_motion
from .linearised import Linearised
from .residual_map import benjamini_hochberg

VISIBLE_MIN = 0.05
Q_FDR = 0.05
STRETCHES = 20  # contiguous stretches of time, each held out in turn
HELDOUT_Z = 1.645  # one-sided 5 %: a finding must predict held-out data significantly better
WARMUP_TAUS_S = (30.0, 120.0, 600.0)  # the selection's grid (Bonferroni over it)
TAU_PROFILE_S = np.geomspace(10.0, 3000.0, 25)  # an accepted warm-up's time constant is profiled over these
NONCENTRALITY_80 = 7.85  # chi2_1 noncentrality for 80 % power at alpha = 0.05
BLOCK_S = 5.0  # time blocks of the wild bootstrap (rows within a block keep their signs together)
BOOT_DRAWS = 999
LONG_BLOCKS = 16  # the wild bootstrap's blocks for a sensor whose noise floor misfits (``time_blocks``)
RIGID = 1e3  # weight on the walks' increments when the visible fraction is measured (q / 1e6)
LAG_MIN_S = SMOOTH_S  # s: a shorter fitted thermal lag is the read-out's quantisation
WHITENED = "whitened"  # a term judged on every row it reaches, whitened (the gyro's inside motions)
EARTH_IMPLAUSIBLE = 1.2  # a vertical rate above this many Earth rates is not Earth's
EARTH_AGREE_SD = 3.0  # with the latitude known, a vertical rate this close to Earth's (in its sd) is Earth's
SIZE_EFFECT = "a lever arm per accelerometer axis (a size effect: each axis senses at its own point)"
UNTESTED = {
    "gyro_saturation": "not a term to fit: clipped gyro samples sit on the rails of the full scale; the "
                       "motions holding them are left out of the fits and reported as saturation events",
    "mag_current_interference": "the magnetometer is mapped (rest magnitude and dip, within-rest scatter) "
                                "but has no score model yet: a flagged magnetometer cell is reported as unknown",
    "mag_field_gradient": "the magnetometer is mapped (rest magnitude and dip, within-rest scatter) "
                          "but has no score model yet: a flagged magnetometer cell is reported as unknown",
    "bias_random_walk": "modelled in the nominal fit (the bias walks of both triads)",
}
REVEAL = {
    "lever_arm": "fast rotations (several rad/s) about axes through different points of the unit",
    "accel_gyro_time_offset": "motions with large, quick changes of orientation",
    "accel_nonlinearity": "rests at many orientations with each axis along +g and -g",
    "accel_scale_temperature": "rests at several orientations repeated across a wide temperature range",
    "bias_temperature_nonlinear": "rests spread over a wide temperature range (a thermal sweep)",
    "gyro_g_sensitivity": "long rests at many orientations (each axis up and down)",
    "earth_rotation": "long rests at many orientations; the latitude known (it fixes the vertical rate)",
    "warmup_transient": "a cold start with rests in the first minutes after power-on",
    "gyro_scale_temperature": "large rotations about every axis repeated across a wide temperature range",
    "gyro_scale_asymmetry": "large rotations about every axis, each in one sense only (not undone by its "
                            "reverse about the same axis)",
    "thermal_lag": "a temperature that changes at different rates or reverses (a cool-down, a hot restart) "
                   "with rests throughout; the bias temperature coefficients known",
}


@dataclass
class Candidate:
    """One effect's term: ``columns`` (N, k) whitened d r / d theta; ``to_params`` maps the
    fitted theta to the effect's parameters (effects.md names and units, calibration frame)."""

    effect: str
    sensor: str
    regime: str
    names: list[str]
    columns: np.ndarray
    to_params: object
    extra_dof: int = 0  # profiled nonlinear parameters (tau): tested over a grid
    fixed: dict = field(default_factory=dict)
    rejects: object = None  # theta -> why these parameters are not the effect (None: they may be)
    heldout_sensor: str = ""  # the triad whose held-out rows prove it (default: its own)
    within: tuple[str, np.ndarray] | None = None  # a larger term outside the catalogue: (what, columns)
    profile: object = None  # tau -> the candidate at that time constant (``_profile`` once accepted)


def triads(sensor: str) -> tuple[str, ...]:
    """The triads whose readings a term of ``sensor`` moves (the temperature's, a thermal lag: both,
    along their ``k``)."""
    return ("accel", "gyro") if sensor == "temperature" else (sensor,)


@dataclass
class Tested:
    candidate: Candidate
    projected: np.ndarray
    visible: float
    biases: list[tuple[str, float]]
    mde: float


def _rows3(lin: Linearised, block: str) -> np.ndarray:
    return np.flatnonzero(lin.rows.of(block)).reshape(-1, 3)


class Signals:
    """What the candidates' regressors need, read once off the fitted model: at the rests (their
    means), at the accelerometer samples inside the motions (``*_motion``) and at the gyro samples
    the motions' attitude is integrated from (``*_gyro_motion``). A term acts on every reading,
    so its column covers all three: a bias-like term left out of the motions is one the bias walk
    can copy at the rests for free (the walk moves the motions' readings too), and its score
    collapses."""

    def __init__(self, lin: Linearised):
        model = lin.model
        self.lin, self.model = lin, model
        P = model.unpack(lin.x_g)
        self.S_a = P["S_a"]
        u, u_motion = lin.gravity()
        g = model.g
        self.f_rest = g * u  # (n, 3) model frame
        self.T_rest = model.dT + T_REF_C
        self.rows_a, self.rows_g = _rows3(lin, "accel_rest"), _rows3(lin, "gyro_rest")
        self.W_a, self.W_g = model.W_a, model.W_g
        t_first = model.mid[0] - 0.5 * model.length[0]
        on = np.r_[0.0, model.rests.t_start_s[model.power_on]]

        def since_on(t: np.ndarray) -> np.ndarray:
            """Time since power-on: since the session's first sample, or the last rest after a power cycle."""
            return t - on[np.searchsorted(on, t, "right") - 1]

        self.t_on_rest = since_on(model.mid)
        acc, ms = model.accel, model.motions
        self.rows_m = _rows3(lin, "accel_motion")
        self.has_motion = len(acc.t) > 0
        self.has_gyro_motion = len(ms.t) > 0
        self.T_motion = model.dT_acc + T_REF_C
        self.t_on_motion = since_on(acc.t)
        self.T_gyro_motion = model.dT_gyro + T_REF_C
        self.t_on_gyro_motion = since_on(ms.t)
        # gravity at the gyro's samples: the accel samples' path, or the rests' directions across a
        # motion without samples
        u_g = np.zeros((len(ms.t), 3))
        acc_of = by_motion(acc.motion, ms.count)
        for j, sel in enumerate(by_motion(ms.motion, ms.count)):
            if sel.stop == sel.start:
                continue
            sa = acc_of[j]
            if sa.stop - sa.start >= 2:
                u_g[sel] = np.column_stack([np.interp(ms.t[sel], acc.t[sa], u_motion[sa, i])
                                            for i in range(3)])
            else:
                span = max(ms.end[j] - ms.origin[j], 1e-12)
                lam = np.clip((ms.t[sel] - ms.origin[j]) / span, 0, 1)[:, None]
                u_g[sel] = (1 - lam) * u[model.p[j]] + lam * u[model.qr[j]]
        self.f_gyro_motion = g * u_g / np.maximum(np.linalg.norm(u_g, axis=1, keepdims=True), 1e-12)
        omega, _ = model._rates(P, lin.x_l, derivatives=False)  # (N_g, 3) calibrated, model frame
        self.S_g = np.linalg.inv(P["M_g"])  # model frame -> the gyro's raw axes
        self.x_gyro_motion = omega @ self.S_g.T  # the same in the gyro's axes (sensed)
        self.k = {"accel": P["k_a"], "gyro": P["k_g"]}
        t_last = max(model.rests.t_end_s[-1], ms.t[-1] if len(ms.t) else -np.inf)
        curve = temperature_curve(model, t_first, t_last)
        self.T_rate_rest = temperature_rate(curve, model.rests.t_start_s, model.rests.t_end_s)
        self.T_rate_motion = temperature_rate(curve, acc.t)
        self.T_rate_gyro_motion = temperature_rate(curve, ms.t)
        if self.has_motion:
            self.f_motion = g * u_motion
            self.omega = np.zeros((len(acc.t), 3))
            self.alpha = np.zeros((len(acc.t), 3))
            self.f_dot = np.zeros((len(acc.t), 3))
            for sel, gs in zip(by_motion(acc.motion, ms.count), by_motion(ms.motion, ms.count), strict=True):
                tj, wj = ms.t[gs], omega[gs]
                if len(tj) < 3 or sel.stop - sel.start < 3:
                    continue
                aj = _derivative(wj, tj)
                ta = acc.t[sel]
                self.omega[sel] = np.column_stack([np.interp(ta, tj, wj[:, i]) for i in range(3)])
                self.alpha[sel] = np.column_stack([np.interp(ta, tj, aj[:, i]) for i in range(3)])
                self.f_dot[sel] = _derivative(self.f_motion[sel], ta)

    def column(self, rows: np.ndarray, W: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """(N, k) whitened columns from raw-reading derivatives ``dy`` (n, 3, k) on ``rows`` (n, 3)."""
        N = len(self.lin.r)
        C = np.zeros((N, dy.shape[2]))
        spec = "ij,njk->nik" if W.ndim == 2 else "nij,njk->nik"
        C[rows.ravel()] = -np.einsum(spec, W, dy).reshape(-1, dy.shape[2])
        return C

    def accel_term(self, regressors) -> np.ndarray:
        """(N, k) the column of an accelerometer term on the rest means and the motions' samples;
        ``regressors(at)`` gives d y / d theta (n, 3, k) with ``at`` "rest" or "motion"."""
        C = self.column(self.rows_a, self.W_a, regressors("rest"))
        if self.has_motion:
            C = C + self.column(self.rows_m, self.model.W_sample, regressors("motion"))
        return C

    def gyro_term(self, regressors) -> np.ndarray:
        """(N, k) the column of a gyro term on the rest means and, through the attitude the motions'
        gyro samples integrate to, on the motions' rows (``regressors(at)``, at "rest" or
        "gyro_motion")."""
        C = self.column(self.rows_g, self.W_g, regressors("rest"))
        if self.has_gyro_motion:
            C[self.model.motion_rows] += self.gyro_motion_column(regressors("gyro_motion"))
        return C

    def gyro_motion_column(self, dy, by_rows: bool = False):
        """(len(motion_rows), k) the column of a term ``dy`` (N_g, 3, k), or factored
        (``attitude.RateDerivatives``), added to the motions' gyro samples on the rows it moves
        (``JointModel.motion_rows``), through the attitude they integrate to
        (``JointModel.gyro_columns``; the term in the prediction: r falls); ``by_rows``: as
        ``forward.GyroColumns``, whose slices of rows are formed when read."""
        rows = self.model.gyro_columns(self.lin.x_g, self.lin.x_l, dy, negate=True)
        return rows if by_rows else rows[:]


def temperature_curve(model, t_first: float, t_last: float):
    """The model's temperature (its stream, else its rests' means) as ``temperature.rate_curve``
    over [``t_first``, ``t_last``] s."""
    stream = model._temperature
    if stream is not None and len(stream[0]):
        return rate_curve(*stream, t_first, t_last)
    return rate_curve(model.mid, model.dT + T_REF_C, t_first, t_last, trim=False)


def _derivative(y: np.ndarray, t: np.ndarray, span_s: float = 0.1) -> np.ndarray:
    """d y / d t by a local cubic over ``span_s`` (Savitzky-Golay): differentiating raw noisy
    samples would put noise into the regressors and shrink the fitted term (errors in variables)."""
    dt = float(np.median(np.diff(t)))
    win = int(np.clip(round(span_s / dt) // 2 * 2 + 1, 5, len(t) // 2 * 2 - 1)) if len(t) >= 5 else 0
    if win < 5:
        return np.gradient(y, t, axis=0)
    return _cubic_slope(np.asarray(y, float), win, dt)


def _cubic_slope(y: np.ndarray, win: int, dt: float) -> np.ndarray:
    """The slope of the least-squares cubic through ``win`` (odd) samples of ``y`` (n, ...) around
    each, spaced ``dt``; within ``win // 2`` of an end, of the first or last ``win`` samples' cubic
    (``scipy.signal.savgol_filter(y, win, 3, deriv=1, delta=dt, axis=0)``, without importing
    scipy.signal)."""
    half = win // 2
    x = np.arange(win) - half
    fit = np.linalg.pinv(np.vander(x, 4, increasing=True))  # (4, win): the cubic's coefficients
    slope = np.column_stack([np.zeros(win), np.ones(win), 2 * x, 3 * x**2]) @ fit / dt  # (win, win)
    out = np.empty_like(y)
    out[half:len(y) - half] = sliding_window_view(y, win, axis=0) @ slope[half]
    out[:half] = slope[:half] @ y[:win]
    out[len(y) - half:] = slope[half + 1:] @ y[len(y) - win:]
    return out


def candidates(lin: Linearised, frame: np.ndarray, registry) -> list[Candidate]:
    """The catalogue's terms this recording's rows can carry (``registry``: effects by identifier)."""
    s = Signals(lin)
    Q = frame
    out: list[Candidate] = []

    eff = registry
    if s.has_motion and "lever_arm" in eff:
        R = np.einsum("ij,njk->nik", s.S_a, eff["lever_arm"].regressors({"omega": s.omega, "alpha": s.alpha}))
        C = s.column(s.rows_m, s.model.W_sample, R)
        per_axis = np.zeros((len(R), 3, 9))  # each sensing axis at its own point (a size effect)
        for i in range(3):
            per_axis[:, i, 3 * i:3 * i + 3] = R[:, i]
        out.append(Candidate("lever_arm", "accel", "motion", ["r_x", "r_y", "r_z"], C,
                             lambda th: {"r_m": list(Q.T @ th)},
                             within=(SIZE_EFFECT, s.column(s.rows_m, s.model.W_sample, per_axis))))
    if s.has_motion and "accel_gyro_time_offset" in eff:
        R = eff["accel_gyro_time_offset"].regressors({"f_dot": s.f_dot})
        C = s.column(s.rows_m, s.model.W_sample, np.einsum("ij,njk->nik", s.S_a, R))
        out.append(Candidate("accel_gyro_time_offset", "accel", "motion", ["dt_s"], C,
                             lambda th: {"dt_s": float(th[0])}))
    # the terms below act on every reading: rest means, the motions' accelerometer samples and
    # (gyro) the samples the motions' attitude is integrated from
    x_at = {"rest": s.f_rest @ s.S_a.T, "motion": s.f_motion @ s.S_a.T if s.has_motion else np.zeros((0, 3))}
    T_at = {"rest": s.T_rest, "motion": s.T_motion, "gyro_motion": s.T_gyro_motion}
    t_on_at = {"rest": s.t_on_rest, "motion": s.t_on_motion, "gyro_motion": s.t_on_gyro_motion}
    f_at = {"rest": s.f_rest, "gyro_motion": s.f_gyro_motion}

    def term(sensor: str, regressors) -> np.ndarray:
        return s.accel_term(regressors) if sensor == "accel" else s.gyro_term(regressors)

    if "accel_nonlinearity" in eff:
        C = s.accel_term(lambda at: eff["accel_nonlinearity"].regressors({"x": x_at[at]}))
        out.append(Candidate("accel_nonlinearity", "accel", "all", ["k2_x", "k2_y", "k2_z"], C,
                             lambda th: {"k2": list(th)}))
    if "accel_scale_temperature" in eff:
        C = s.accel_term(lambda at: eff["accel_scale_temperature"].regressors({"x": x_at[at], "T": T_at[at]}))
        out.append(Candidate("accel_scale_temperature", "accel", "static", ["ppm_x", "ppm_y", "ppm_z"], C,
                             lambda th: {"ppm_per_C": list(th)}))
    if "bias_temperature_nonlinear" in eff:
        for sensor in ("accel", "gyro"):
            C = term(sensor, lambda at: eff["bias_temperature_nonlinear"].regressors({"T": T_at[at]}))
            out.append(Candidate("bias_temperature_nonlinear", sensor, "static", ["k2_x", "k2_y", "k2_z"], C,
                                 lambda th, sensor=sensor: {"k2_per_C2": list(th), "sensor": sensor}))
    if "gyro_g_sensitivity" in eff:
        C = s.gyro_term(lambda at: eff["gyro_g_sensitivity"].regressors({"f": f_at[at]}))
        out.append(Candidate("gyro_g_sensitivity", "gyro", "static", [f"G{i}{j}" for i in range(3) for j in range(3)],
                             C, lambda th: {"G": (th.reshape(3, 3) @ Q).tolist()}))
    # the gyro's scale terms act on the rate it senses: none at rest, the motions' through the attitude
    # (most of their evidence is the attitude path's rows, which have no sensor units: judged whitened)
    x_gyro = {"rest": np.zeros_like(s.f_rest), "gyro_motion": s.x_gyro_motion}
    if "gyro_scale_temperature" in eff:
        C = s.gyro_term(lambda at: eff["gyro_scale_temperature"].regressors({"x": x_gyro[at], "T": T_at[at]}))
        out.append(Candidate("gyro_scale_temperature", "gyro", "motion", ["ppm_x", "ppm_y", "ppm_z"], C,
                             lambda th: {"ppm_per_C": list(th)}, heldout_sensor=WHITENED))
    if "gyro_scale_asymmetry" in eff:
        C = s.gyro_term(lambda at: eff["gyro_scale_asymmetry"].regressors({"x": x_gyro[at]}))
        out.append(Candidate("gyro_scale_asymmetry", "gyro", "motion", ["eps_x", "eps_y", "eps_z"], C,
                             lambda th: {"eps": list(th)}, heldout_sensor=WHITENED))
    if "thermal_lag" in eff:
        # the biases follow the die, k (T_die - 25), the model the read-out: both triads read
        # k tau dT_read/dt more (one tau). Its sensor is the temperature's (effects.md); its
        # held-out RMS is in the units of the triad that carries more of it
        rate_at = {"rest": s.T_rate_rest, "motion": s.T_rate_motion, "gyro_motion": s.T_rate_gyro_motion}
        parts = {sensor: term(sensor, lambda at, sensor=sensor: eff["thermal_lag"].regressors(
            {"k": s.k[sensor], "T_rate": rate_at[at]})) for sensor in ("accel", "gyro")}
        sensor = max(parts, key=lambda x: float(np.linalg.norm(parts[x])))
        C = parts["accel"] + parts["gyro"]
        tau_of = _lag_of(lin, C, sensor)
        out.append(Candidate("thermal_lag", "temperature", "static", ["tau_s"], C,
                             lambda th: {"tau_s": tau_of(th)}, rejects=lambda th: _not_a_lag(tau_of(th)),
                             heldout_sensor=sensor))
    if "earth_rotation" in eff:
        # at rest Earth's rate has a vertical part along gravity (Omega sin(lat), the same in every
        # rest: an isotropic g-sensitivity G = (Omega sin(lat) / g) I) and a horizontal part that
        # turns with the heading, which no rest fixes (left to the bias walk). One column, against
        # the nine of gyro_g_sensitivity: the selection names whichever explains the rests
        # with fewer parameters. The gyro senses it as an input: through its scale matrix.
        def vertical(at: str) -> np.ndarray:
            up = f_at[at] / np.maximum(np.linalg.norm(f_at[at], axis=1, keepdims=True), 1e-12)
            R = eff["earth_rotation"].regressors({"north": np.zeros_like(up), "up": up})[:, :, 1:]
            return np.einsum("ij,njk->nik", s.S_g, R)

        out.append(Candidate("earth_rotation", "gyro", "static", ["Omega_sin_lat"], s.gyro_term(vertical),
                             _latitude))
    if "warmup_transient" in eff:
        def warmup(sensor: str, tau: float) -> Candidate:
            p = {"amp": [0, 0, 0], "tau_s": tau, "sensor": sensor}
            C = term(sensor, lambda at: eff["warmup_transient"].regressors({"t_on": t_on_at[at]}, p))
            return Candidate("warmup_transient", sensor, "warmup", ["amp_x", "amp_y", "amp_z"], C,
                             lambda th: {"amp": list(th), "tau_s": tau, "sensor": sensor},
                             extra_dof=len(WARMUP_TAUS_S), fixed={"tau_s": tau}, profile=partial(warmup, sensor))

        out += [warmup(sensor, tau) for sensor in ("accel", "gyro") for tau in WARMUP_TAUS_S]
    return [c for c in out if np.any(c.columns)]


def _lag_of(lin: Linearised, C: np.ndarray, sensor: str):
    """theta -> the lag, s. The column is ``k^ dT/dt`` along the calibration's ``k^``, which the lag
    itself biased (a fit of the read-out's k absorbs part of ``k tau dT/dt``); refitted with the
    term, the globals give the ``k`` the lag acts along: ``tau = theta (k^ . k) / (k . k)``."""
    key = "k_a" if sensor == "accel" else "k_g"
    sl = lin.model.glob.slices.get(key)
    if sl is None:  # k held at the calibration's: nothing to refit
        return lambda th: float(th[0])
    k_hat = lin.model.unpack(lin.x_g)[key]
    z_r = lin.system.solve(lin.J_g.T @ lin.r, lin.J_l.T @ lin.r)[0][sl]
    z_c = project(lin, C)[1][sl, 0]

    def tau(th: np.ndarray) -> float:
        k = k_hat - z_r - z_c * float(th[0])
        return float(th[0]) * float(k_hat @ k) / max(float(k @ k), 1e-300)
    return tau


def _not_a_lag(tau: float) -> str | None:
    """Why a fitted lag is not the die's: shorter than the temperature smoother, it is what the
    read-out's steps leave in the de-quantised temperature (memo E15), and a negative one is a lead."""
    if tau < 0:
        return f"a thermal lag of {tau:.3g} s would be the read-out leading the die, not lagging it"
    if tau < LAG_MIN_S:
        return (f"a thermal lag of {tau:.3g} s is below the temperature smoother's {LAG_MIN_S:g} s: "
                "the read-out's quantisation, not the die lagging its sensor")
    return None


def _latitude(th: np.ndarray) -> dict:
    """Earth rate's vertical component (``Omega sin(lat)``) -> latitude (``diagnose`` renames a
    vertical rate beyond Earth's an isotropic gyro g-sensitivity)."""
    return {"latitude_deg": float(np.degrees(np.arcsin(np.clip(float(th[0]) / EARTH_RATE, -1, 1))))}


def project(lin: Linearised, C: np.ndarray, system: Bordered | None = None,
            J_l: sp.csr_matrix | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(I - P) C`` and the nominal globals' shift per unit of each column, ``z_g`` (P_g, k);
    ``system``/``J_l``: another normal system of the same Jacobian (``rigid_walks``)."""
    if system is None and J_l is None:
        return lin.project(C)
    system = lin.system if system is None else system
    J_l = lin.J_l if J_l is None else J_l
    z_g, z_l = system.solve(lin.J_g.T @ C, J_l.T @ C)
    return C - lin.J_g @ z_g - J_l @ z_l, z_g


def rigid_walks(lin: Linearised) -> tuple[Bordered, sp.csr_matrix]:
    """The fit's normal system with the bias walks held (nearly) still: their increments' rows
    weighted ``RIGID``-fold. What a term loses to this projection the nominal *parameters* make
    (calibration, gravity directions, a new turn-on bias after a power cycle): the visible
    fraction. What the walks take on top is noise they can mimic: it costs power (the
    information and minimum detectable size say how much), it does not hide the term."""
    # the values scaled, the pattern shared (no second copy of J_l's indices); the walks' rows
    # are a few runs: their entries scaled in place (no per-entry weight array at the map's peak)
    data, ptr = lin.J_l.data.copy(), lin.J_l.indptr
    for a, b in _walk_runs(lin):
        data[ptr[a]:ptr[b]] *= RIGID
    J_l = sp.csr_matrix((data, lin.J_l.indices, ptr), shape=lin.J_l.shape)
    return Bordered(lin.J_g, J_l, lin.model.stages.offsets), J_l


def rigid_solver(lin: Linearised) -> Bordered:
    """``rigid_walks``' system for its solves alone (``Bordered.solver_only``), factored with the
    walks' rows scaled in J_l's own values and those few values restored after: no copy of
    J_l's values (the structure cells' peak); the same factors."""
    data, ptr = lin.J_l.data, lin.J_l.indptr
    runs = _walk_runs(lin)
    kept = [data[ptr[a]:ptr[b]].copy() for a, b in runs]
    try:
        for a, b in runs:
            data[ptr[a]:ptr[b]] *= RIGID
        return Bordered(lin.J_g, lin.J_l, lin.model.stages.offsets).solver_only()
    finally:
        for (a, b), values in zip(runs, kept, strict=True):
            data[ptr[a]:ptr[b]] = values


def _walk_runs(lin: Linearised) -> list[tuple[int, int]]:
    """The runs [a, b) of the bias walks' increment rows."""
    walk = lin.rows.of("walk_gyro") | lin.rows.of("walk_accel")
    edges = np.flatnonzero(np.diff(np.r_[False, walk, False]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def examine(lin: Linearised, c: Candidate, rigid: tuple[Bordered, sp.csr_matrix] | None = None) -> Tested:
    """The candidate's projection, visible fraction (against ``rigid``, default the fit's own
    system), the parameters it would bias and its minimum detectable size."""
    Cp, z_g = project(lin, c.columns)
    Cv = project(lin, c.columns, *rigid)[0] if rigid is not None else Cp
    A, B = c.columns.T @ c.columns, Cp.T @ Cp
    L = np.linalg.cholesky(A + 1e-300 * np.eye(len(A)))
    Li = np.linalg.inv(L)
    visible = float(np.sqrt(np.clip(np.linalg.eigvalsh(Li @ (Cv.T @ Cv) @ Li.T).min(), 0, 1)))
    names = lin.globals.names()
    strength = np.abs(z_g).max(axis=1)
    biases = [(names[i], float(strength[i])) for i in np.argsort(strength)[::-1][:3] if strength[i] > 0]
    # smallest effect (along the term's weakest direction) the test sees at 80 % power
    lam_min = np.linalg.eigvalsh(B).min()
    mde = float(np.sqrt(NONCENTRALITY_80 / lam_min)) if lam_min > 0 else float("inf")
    return Tested(c, Cp, visible, biases, mde)


def _score(r: np.ndarray, Cp: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
    B = Cp.T @ Cp
    g = Cp.T @ r
    theta = np.linalg.lstsq(B, g, rcond=None)[0]
    return float(g @ theta) / scale, theta


def time_blocks(lin: Linearised, long: bool = False) -> np.ndarray:
    """(N,) the ``BLOCK_S`` time block of every row of the fit: the wild bootstrap's units;
    ``long``: ``LONG_BLOCKS`` equal spans of the recording (not shorter than ``BLOCK_S``)."""
    t = np.nan_to_num(lin.rows.t)
    block_s = max(BLOCK_S, float(np.ptp(t)) / LONG_BLOCKS) if long and len(t) else BLOCK_S
    return np.floor(t / block_s).astype(np.int64)


def wild_p(Cp: np.ndarray, r: np.ndarray, groups: np.ndarray, draws: int = BOOT_DRAWS) -> float:
    """p-value of the score statistic ``r' Cp (Cp' Cp)^-1 Cp' r`` by a wild bootstrap over time
    blocks (``groups``: each row's block): every draw flips the sign of whole blocks of the
    residual. It keeps the recording's own noise -- correlated within a block, of any size and
    shape -- and needs no noise model; a term that is really there is consistent across blocks
    and stands out of the flipped draws. Deterministic (seeded)."""
    _, inv = np.unique(groups, return_inverse=True)
    G = inv.max() + 1
    g_b = np.column_stack([np.bincount(inv, Cp[:, j] * r, G) for j in range(Cp.shape[1])])  # (G, k)
    return block_wild_p(g_b, Cp.T @ Cp, draws)


def block_wild_p(g_b: np.ndarray, B: np.ndarray, draws: int = BOOT_DRAWS) -> float:
    """``wild_p`` from each block's score ``g_b`` (G, k), the sum over its rows of ``Cp * r``,
    and the term's information ``B = Cp' Cp`` (k, k)."""
    Binv = np.linalg.pinv(B)
    g = g_b.sum(0)
    T = float(g @ Binv @ g)
    signs = np.random.default_rng(0).choice([-1.0, 1.0], (draws, len(g_b)))
    gs = signs @ g_b
    T_star = np.einsum("dk,kl,dl->d", gs, Binv, gs)
    return float((1 + np.sum(T_star >= T)) / (draws + 1))


def _orth(X: np.ndarray, A: np.ndarray | None) -> np.ndarray:
    if A is None or not A.shape[1]:
        return X
    return X - A @ np.linalg.lstsq(A, X, rcond=None)[0]


@dataclass
class Finding:
    tested: Tested
    statistic: float
    p_value: float
    delta_bic: float
    theta: np.ndarray = None  # type: ignore[assignment]
    p_asymptotic: float = float("nan")  # chi-square's, before the bootstrap's floor of 1/(draws + 1)
    rivals: list[str] = field(default_factory=list)  # effects that explain it as well (``_rivals``)
    beyond: str = ""  # a larger term outside the catalogue significant beyond it (``_within_larger``)
    tau_sd: float = 0.0  # a profiled time constant's 1-sigma (``_profile``)
    dtheta_dtau: np.ndarray | None = None  # theta's change per second of it


def select(lin: Linearised, tested: list[Tested], q: float = Q_FDR, latitude_deg: float | None = None,
           misfit: frozenset[str] = frozenset()) -> tuple[np.ndarray, list[Finding]]:
    """Forward selection with BH at each step and a backward check; returns the residual
    with the nominal globals refitted (``rp``) and the accepted findings (theta fitted jointly).
    ``latitude_deg``: the recording's, when known (``_earth_rivals``); ``misfit``: the sensors
    whose noise floor the residual map finds misfit (their bootstrap's blocks are long)."""
    z_g, z_l = lin.system.solve(lin.J_g.T @ lin.r, lin.J_l.T @ lin.r)
    rp = lin.r - lin.J_g @ z_g - lin.J_l @ z_l  # the globals refitted too (Gauss-Newton step)
    n_rows = len(rp)
    pool = [t for t in tested if t.visible >= VISIBLE_MIN]
    accepted: list[Finding] = []

    groups = {long: time_blocks(lin, long) for long in (False, True)}

    def stat(t: Tested, others: list[Finding]) -> tuple[float, float, float]:
        """Score statistic, its p-value (the larger of the asymptotic and the wild bootstrap's)
        and the asymptotic one (which ranks the candidates: the bootstrap's floors at 1/1000)."""
        A = np.hstack([f.tested.projected for f in others]) if others else None
        Cp = _orth(t.projected, A)
        r = _orth(rp, A)
        rows = np.any(t.candidate.columns != 0, axis=1)
        dof = max(rows.sum() - Cp.shape[1], 1)
        scale = max(1.0, float(r[rows] @ r[rows]) / dof)
        T, _ = _score(r, Cp, scale)
        k = Cp.shape[1]
        bonferroni = max(1, t.candidate.extra_dof)
        p_asym = min(1.0, float(tails.chi2_sf(T, k)) * bonferroni)
        blocks = groups[bool(misfit.intersection(triads(t.candidate.sensor)))]
        p = p_asym if p_asym > q else max(p_asym, min(1.0, wild_p(Cp, r, blocks) * bonferroni))
        return T, p, p_asym

    while True:
        taken = {(f.tested.candidate.effect, f.tested.candidate.sensor) for f in accepted}
        rest = [t for t in pool if (t.candidate.effect, t.candidate.sensor) not in taken]
        if not rest:
            break
        scored = [(t, *stat(t, accepted)) for t in rest]
        p = np.array([s[2] for s in scored])
        ok = benjamini_hochberg(p, q)
        if not ok.any():
            break
        best = min((s for s, o in zip(scored, ok) if o), key=lambda s: s[3])
        t, T, pv, pa = best
        accepted.append(Finding(t, T, pv, -T + t.projected.shape[1] * np.log(n_rows), p_asymptotic=pa))
        # backward check
        for f in list(accepted):
            others = [g for g in accepted if g is not f]
            T2, p2, pa2 = stat(f.tested, others)
            if p2 > q:
                accepted.remove(f)
            else:
                f.statistic, f.p_value, f.p_asymptotic = T2, p2, pa2
                f.delta_bic = -T2 + f.tested.projected.shape[1] * np.log(n_rows)
        if best[0] not in [f.tested for f in accepted]:
            break
    _earth_or_g(accepted, pool, stat, n_rows)
    _rivals(accepted, tested, stat, q)  # a rival too faint to be named can still explain it as well
    _within_larger(lin, accepted, stat, q)
    for f in accepted:
        if f.tested.candidate.profile is not None:
            _profile(lin, f, [g for g in accepted if g is not f], rp)
    if accepted:
        A = np.hstack([f.tested.projected for f in accepted])
        theta = -np.linalg.lstsq(A, rp, rcond=None)[0]  # r(theta) = rp + A theta, minimised
        o = 0
        for f in accepted:
            k = f.tested.projected.shape[1]
            f.theta = theta[o:o + k]
            o += k
    _earth_rivals(accepted, pool, rp, latitude_deg)
    return rp, accepted


def _profile(lin: Linearised, f: Finding, others: list[Finding], rp: np.ndarray) -> None:
    """An accepted term's time constant profiled (in place): its score given ``others`` over
    ``TAU_PROFILE_S``, the maximum refined by Newton steps in log tau, the term re-examined there.
    The selection's grid (Bonferroni over it) is what its p-value stands on; this is its estimate,
    with the 1-sigma where the score has dropped by 1 (the profile likelihood's) and the linear
    parameters' change per second of tau, which widens their sd (``theta_cov``)."""
    A = np.hstack([g.tested.projected for g in others]) if others else None
    r = _orth(rp, A)
    c = f.tested.candidate
    rows = np.any(c.columns != 0, axis=1)
    scale = max(1.0, float(r[rows] @ r[rows]) / max(int(rows.sum()) - c.columns.shape[1], 1))

    def score(tau: float) -> tuple[float, np.ndarray]:
        return _score(r, _orth(project(lin, c.profile(tau).columns)[0], A), scale)

    x = np.log(TAU_PROFILE_S)
    x_hat = float(x[np.argmax([score(tau)[0] for tau in TAU_PROFILE_S])])
    d, curvature = 0.05, 0.0
    for _ in range(4):  # Newton in log tau on central differences: the maximum and its curvature
        T_lo, T_0, T_hi = (score(float(np.exp(x_hat + e)))[0] for e in (-d, 0.0, d))
        curvature = (T_hi + T_lo - 2 * T_0) / (2 * d * d)
        if curvature >= 0:
            break
        step = float(np.clip(-(T_hi - T_lo) / (4 * d * curvature), -0.12, 0.12))
        x_hat += step
        if abs(step) < 0.01:
            break
    tau = float(np.exp(x_hat))
    # the score is twice the log-likelihood gained: tau's 1-sigma is where it has dropped by 1 (a
    # profile that does not bend down leaves tau undetermined: its sd is tau itself)
    f.tau_sd = tau / np.sqrt(-curvature) if curvature < 0 else tau
    h = 1e-3 * tau
    f.dtheta_dtau = -(score(tau + h)[1] - score(tau - h)[1]) / (2 * h)  # theta = -score's (``select``)
    f.tested = replace(examine(lin, c.profile(tau)), visible=f.tested.visible)


def _rivals(accepted: list[Finding], pool: list[Tested], stat, q: float) -> None:
    """The naming traps this recording cannot resolve (in place): a rival catalogue term (any
    tested one, also one too little visible to be named itself) that is significant in an accepted
    one's place while the accepted one adds nothing significant beyond it (a warm-up transient and
    a thermal lag when the lag's start-up falls in one long rest).
    Neither name is then stood behind (``diagnose`` reports an ``unknown`` naming both). A rival
    whose columns contain the accepted one's (Earth's vertical rate inside a g-sensitivity) is
    a parsimony question, ``_earth_or_g``'s."""
    for f in accepted:
        others = [g for g in accepted if g is not f]
        for t in pool:
            if t.candidate.effect == f.tested.candidate.effect or t.candidate.effect in f.rivals \
                    or any(t is g.tested for g in accepted) or _within(f.tested.projected, t.projected):
                continue
            if stat(t, others)[1] > q:
                continue
            if stat(f.tested, others + [Finding(t, 0.0, 0.0, 0.0)])[1] > q:
                f.rivals.append(t.candidate.effect)


def _within_larger(lin: Linearised, accepted: list[Finding], stat, q: float) -> None:
    """The trap of a term that is a special case of a larger one outside the catalogue (in place):
    one lever arm inside a lever arm per axis. Where the larger term's further directions are
    significant beyond the accepted terms, the term explains only part of the structure and is
    not stood behind alone (``Finding.beyond``; ``diagnose`` reports an ``unknown`` naming it).
    Nor is another accepted term of its sensor that adds nothing significant beyond the larger
    term: it took up part of the larger term's structure (measured: a 5-mm size effect on gimbal
    seed 0 gave the lever arm inside it and an accelerometer nonlinearity, p 0.003)."""
    for f in accepted:
        c = f.tested.candidate
        if c.within is None:
            continue
        name, columns = c.within
        extra = _orth(project(lin, columns)[0], f.tested.projected)
        _, sv, Vt = np.linalg.svd(extra, full_matrices=False)
        extra = extra @ Vt[sv > 1e-8 * sv.max()].T  # the larger term's own directions only
        larger = Tested(Candidate(name, c.sensor, c.regime, [], columns, lambda th: {}), extra, 1.0, [], np.inf)
        if stat(larger, accepted)[1] <= q:
            f.beyond = name
            for g in accepted:
                if g is f or g.beyond or g.tested.candidate.sensor != c.sensor:
                    continue
                others = [h for h in accepted if h is not g] + [Finding(larger, 0.0, 0.0, 0.0)]
                if stat(g.tested, others)[1] > q:
                    g.beyond = name


def _within(A: np.ndarray, B: np.ndarray) -> bool:
    """The columns of ``A`` lie in the span of ``B``'s."""
    return float(np.linalg.norm(_orth(A, B))) <= 1e-6 * float(np.linalg.norm(A))


def _earth_or_g(accepted: list[Finding], pool: list[Tested], stat, n_rows: int) -> None:
    """The naming trap of the rests: Earth's vertical rate is an isotropic g-sensitivity
    (G = Omega sin(lat) / g I). An accepted G whose eight further parameters explain less than
    BIC asks of them over the one Earth-rate column is Earth's rate (in place)."""
    g = next((f for f in accepted if f.tested.candidate.effect == "gyro_g_sensitivity"), None)
    e = next((t for t in pool if t.candidate.effect == "earth_rotation"), None)
    if g is None or e is None or any(f.tested is e for f in accepted):
        return
    others = [f for f in accepted if f is not g]
    T_g, *_ = stat(g.tested, others)
    T_e, p_e, pa_e = stat(e, others)
    extra = g.tested.projected.shape[1] - e.projected.shape[1]
    if T_g - T_e < extra * np.log(n_rows) and p_e <= g.p_value * 1e3:
        accepted[accepted.index(g)] = Finding(e, T_e, p_e, -T_e + e.projected.shape[1] * np.log(n_rows),
                                                p_asymptotic=pa_e)


def theta_cov(rp: np.ndarray, f: Finding, others: list[Finding]) -> np.ndarray:
    """(k, k) covariance of ``f``'s theta in the linearised joint fit with ``others``, scaled by its
    rows' chi2/dof when above 1 (as its test is)."""
    A = np.hstack([g.tested.projected for g in others] + [f.tested.projected])
    k = f.tested.projected.shape[1]
    rows = np.any(f.tested.candidate.columns != 0, axis=1)
    left = rp - A @ np.linalg.lstsq(A, rp, rcond=None)[0]
    scale = max(1.0, float(left[rows] @ left[rows]) / max(int(rows.sum()) - k, 1))
    cov = np.linalg.pinv(A.T @ A)[-k:, -k:] * scale
    if f.dtheta_dtau is not None:  # a profiled time constant's uncertainty carried to theta
        cov = cov + f.tau_sd ** 2 * np.outer(f.dtheta_dtau, f.dtheta_dtau)
    return cov


def _earth_rivals(accepted: list[Finding], pool: list[Tested], rp: np.ndarray,
                  latitude_deg: float | None = None) -> None:
    """The naming trap the parsimony rule leaves (in place): a vertical rate Earth can make is, at
    rest, an isotropic g-sensitivity as well; without the latitude neither is stood behind (a
    rate beyond ``EARTH_IMPLAUSIBLE`` Earth rates is the g-sensitivity, ``diagnose`` names it).
    With the latitude known, a rate within ``EARTH_AGREE_SD`` of Earth's there is Earth's."""
    if not any(t.candidate.effect == "gyro_g_sensitivity" for t in pool):
        return
    for f in accepted:
        if f.tested.candidate.effect != "earth_rotation" or abs(f.theta[0]) > EARTH_IMPLAUSIBLE * EARTH_RATE \
                or "gyro_g_sensitivity" in f.rivals:
            continue
        if latitude_deg is not None:
            sd = np.sqrt(theta_cov(rp, f, [g for g in accepted if g is not f])[0, 0])
            if abs(f.theta[0] - EARTH_RATE * np.sin(np.radians(latitude_deg))) <= EARTH_AGREE_SD * sd:
                continue
        f.rivals.append("gyro_g_sensitivity")


def raw_units(lin: Linearised, r: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per sensor: its residual rows (accel rest + motion, gyro rest) un-whitened, in sensor
    units; each row's group id (rest ``i`` -> i, motion sample of motion ``j`` -> n + j); and
    the same rows whitened."""
    model = lin.model
    out = {}
    ra, rg, rm = _rows3(lin, "accel_rest"), _rows3(lin, "gyro_rest"), _rows3(lin, "accel_motion")
    n = model.n
    e_a = np.linalg.solve(model.W_a, r[ra][:, :, None])[:, :, 0]
    W_m = np.broadcast_to(model.W_sample, (len(rm), 3, 3))  # one whitener, or one per sample (pooled)
    e_m = np.linalg.solve(W_m, r[rm][:, :, None])[:, :, 0]
    out["accel"] = (np.vstack([e_a, e_m]), np.r_[np.arange(n), n + model.accel.motion], np.vstack([r[ra], r[rm]]))
    out["gyro"] = (np.linalg.solve(model.W_g, r[rg][:, :, None])[:, :, 0], np.arange(n), r[rg])
    return out


def _row_groups(lin: Linearised, paths: bool = False) -> np.ndarray:
    """(N,) the rest (``i``) or motion (``n + j``) of every data row, -1 for prior rows;
    ``paths``: a motion's attitude-path rows (``turn``: the gyro's evidence inside it) count as its."""
    model = lin.model
    groups = np.full(len(lin.r), -1)
    for name in ("accel_rest", "gyro_rest"):
        rows = _rows3(lin, name)
        groups[rows] = np.arange(len(rows))[:, None]
    rm = _rows3(lin, "accel_motion")
    if len(rm):
        groups[rm] = (model.n + model.accel.motion)[:, None]
    if paths:
        turn = lin.rows.of("turn")
        groups[turn] = model.n + lin.rows.index[turn]
    return groups


class HeldOut(NamedTuple):
    """A finding's held-out check: RMS (sensor units) without and with its term, the z-score of
    the improvement, and the predictive chi2 per held-out row without and with it (nan where the
    check has none)."""

    rms_before: float
    rms_after: float
    z: float
    chi2_n_before: float = float("nan")
    chi2_n_after: float = float("nan")


def _stretch_of_rows(lin: Linearised, stretches: int = STRETCHES, session: np.ndarray | None = None) -> np.ndarray:
    """(N,) the stretch of every data row (-1: prior rows, in every training set): the recording
    cut into ``stretches`` contiguous stretches of time, each rest and each motion whole in one;
    with ``session`` (N,: each row's), every session cut into ``stretches`` of its own."""
    groups = _row_groups(lin)
    used = groups >= 0
    g = groups[used]
    t_group = np.bincount(g, lin.rows.t[used]) / np.maximum(np.bincount(g), 1)
    s_group = np.zeros(len(t_group), int)
    if session is not None:
        s_group[g] = session[used]
    order = np.flatnonzero(np.bincount(g) > 0)
    order = order[np.lexsort((t_group[order], s_group[order]))]
    s = s_group[order]
    count = np.bincount(s)
    first = np.cumsum(count) - count
    of_group = np.full(len(t_group), -1)
    of_group[order] = s * stretches + (np.arange(len(order)) - first[s]) * stretches // count[s]
    stretch = np.full(len(lin.r), -1)
    stretch[used] = of_group[g]
    return stretch


def _refit_predict(lin: Linearised, J: np.ndarray, k_base: int, train: np.ndarray,
                   targets: tuple[np.ndarray, ...] = ()) -> list[tuple[np.ndarray, np.ndarray]]:
    """The residual on every row after a Gauss-Newton refit of the globals, every nuisance and the
    term columns to the ``train`` rows (the priors always count), ``J`` (N, P_g + k) the globals'
    Jacobian beside the term columns: without the last ``k - k_base`` columns and with them; for
    the fit's residual and then each of ``targets`` (residual vectors refitted the same way). One
    factorisation of the system serves all. ``J``'s other rows are zeroed while the system and
    its right-hand sides are formed, then restored (no weighted copy as large as ``J``)."""
    w = train.astype(float)
    held = np.flatnonzero(~train)
    kept = J[held]
    J[held] *= 0.0  # as J * w: the same bits
    try:
        Jl = (sp.diags(w) @ lin.J_l).tocsr()
        system = Bordered(J, Jl, lin.model.stages.offsets)
        rhs = [(-(J.T @ (r * w)), -np.asarray(Jl.T @ (r * w))) for r in (lin.r, *targets)]
    finally:
        J[held] = kept
    out = []
    for r, (g_g, g_l) in zip((lin.r, *targets), rhs, strict=True):
        y = system.blocks.solve(g_l)
        pair = []
        for P in (lin.J_g.shape[1] + k_base, J.shape[1]):
            x_g = np.linalg.solve(system.S[:P, :P], g_g[:P] - system.A_lg[:, :P].T @ y)
            x_l = y - system.X[:, :P] @ x_g
            pair.append(r + J[:, :P] @ x_g + lin.J_l @ x_l)
        out.append((pair[0], pair[1]))
    return out


def heldout(lin: Linearised, rp: np.ndarray, finding: Finding, others: list[Finding],
            stretch: np.ndarray | None = None) -> HeldOut:
    """Blocked cross-validated RMS (sensor units) of the finding's sensor rows without and with
    its term (others already accepted are in both), and the z-score of the improvement: the
    predictive chi2's decrease over the stretches (``_predictive_chi2``, ``_gain_z``). Each
    of ``STRETCHES`` contiguous stretches of time (whole rests and motions) is held out in turn:
    the calibration, every nuisance (bias walks, gravity directions, attitude paths) and the terms
    are refitted without it (one linearised step) and its rows predicted. A bias walk fitted to
    the rows it is judged on would pass for any slow term there, and it bridges single held-out
    rests as well as the term does. A motion term is held out by single rests and motions
    (``_heldout_projected``): only its motion's own attitude path could copy it, and a held-out
    motion is whole. ``stretch`` (N,): other stretches (``_stretch_of_rows``' face)."""
    if finding.tested.candidate.regime == "motion":
        return _heldout_projected(lin, rp, finding, others)
    stretch = _stretch_of_rows(lin) if stretch is None else stretch
    J = np.hstack([lin.J_g] + [f.tested.candidate.columns for f in others] + [finding.tested.candidate.columns])
    k_base = J.shape[1] - lin.J_g.shape[1] - finding.tested.candidate.columns.shape[1]
    signal = finding.tested.candidate.columns @ finding.theta  # the term as fitted to every row
    before, after = np.zeros_like(rp), np.zeros_like(rp)
    added, expected = [], []
    try:
        whole, whole_signal = _refit_predict(lin, J, k_base, np.ones(len(rp), bool), (signal,))
        for k in np.unique(stretch[stretch >= 0]):
            test = stretch == k
            (b, a), held_signal = _refit_predict(lin, J, k_base, ~test, (signal,))
            if not (np.all(np.isfinite(b[test])) and np.all(np.isfinite(a[test]))):
                raise SolverError("a stretch leaves a nuisance undetermined")
            before[test], after[test] = b[test], a[test]
            added.append(_predictive_chi2(whole, (b, a), ~test))
            expected.append(np.subtract(*_predictive_chi2(whole_signal, held_signal, ~test)))
    except (np.linalg.LinAlgError, SolverError):  # a stretch whose removal leaves a nuisance free
        return _heldout_projected(lin, rp, finding, others)
    added = np.array(added)
    chi2_n = added.sum(0) / np.sum(stretch >= 0)
    return _sensor_rms(lin, finding, before, after, (_gain_z(added[:, 0] - added[:, 1], np.array(expected)), *chi2_n))


def _predictive_chi2(whole: tuple[np.ndarray, np.ndarray], held: tuple[np.ndarray, np.ndarray],
                     train: np.ndarray) -> tuple[float, float]:
    """A held-out stretch's predictive chi2 without and with the term: what it adds to the fitted
    chi2 (``whole``: the residuals without and with the term fitted to every row; ``held``:
    fitted to the ``train`` rows). For the linearised model that is its residual judged by its
    whole predictive covariance: the measurement noise, the calibration's uncertainty and a
    walk's across the gap."""
    b, a = (float(w @ w - h[train] @ h[train]) for w, h in zip(whole, held))  # without, with
    return b, a


def _gain_z(gains: np.ndarray, expected: np.ndarray) -> float:
    """z-score of the held-out units' predictive chi2 decrease ``gains``: their sum against its
    standard error. ``expected`` is each unit's decrease were the data the fitted term alone
    (noise-free: its evidence ``q``); a unit's gain is ``q`` plus noise of variance ``4 q``
    under the model, the scale inflated by how much the units scatter beyond that. Some units
    carry most of a term's evidence (the turntable's turns, the rests that see Earth's rate):
    a t-test over the units would count that spread of the signal as noise. An inflation
    estimated from the units makes the ratio Student's t (units - 1 dof), returned as the
    normal score of the same one-sided p."""
    q = float(expected.sum())
    if q <= 0:
        return 0.0
    inflation = float(np.sum((gains - expected) ** 2)) / (4 * q)
    t = float(gains.sum() / (2 * np.sqrt(max(inflation, 1.0) * q)))
    if inflation <= 1.0 or len(gains) < 2:
        return t
    return float(tails.norm_isf(tails.t_sf(t, len(gains) - 1)))


def _sensor_rms(lin: Linearised, finding: Finding, before: np.ndarray, after: np.ndarray,
                proof: tuple[float, ...] | None = None) -> HeldOut:
    """Held-out RMS of the finding's sensor rows without and with the term (``WHITENED``: of
    every row it reaches, whitened) and ``proof`` (z, predictive chi2/n without and with); without
    it, the z-score of the whitened squared error's decrease (the model's own weights: a precise
    rest mean counts for more than a noisy motion sample) summed per rest and per motion, its
    mean over them against its standard error (paired; positive: the term predicts better)."""
    sensor = finding.tested.candidate.heldout_sensor or finding.tested.candidate.sensor
    rows = np.any(finding.tested.candidate.columns != 0, axis=1)
    if sensor == WHITENED:
        group = _row_groups(lin, paths=True)
        rows &= group >= 0
        e0, e1, group = before[rows][:, None], after[rows][:, None], group[rows]
        w0, w1 = e0, e1
    else:
        e0, group, w0 = raw_units(lin, np.where(rows, before, 0))[sensor]
        e1, _, w1 = raw_units(lin, np.where(rows, after, 0))[sensor]
    used = np.any(e0 != 0, axis=1)
    if not used.any():
        return HeldOut(float("nan"), float("nan"), float("nan"))
    rms = lambda e: float(np.sqrt(np.mean(e[used] ** 2)))  # noqa: E731
    if proof is None:
        _, where = np.unique(group[used], return_inverse=True)
        d = np.bincount(where, (w0[used] ** 2 - w1[used] ** 2).sum(axis=1))
        sd = float(np.std(d, ddof=1)) if len(d) > 1 else 0.0
        proof = (float(np.mean(d) / (sd / np.sqrt(len(d)))) if sd > 0 else 0.0,)
    return HeldOut(rms(e0), rms(e1), *map(float, proof))


def _heldout_projected(lin: Linearised, rp: np.ndarray, finding: Finding, others: list[Finding]) -> HeldOut:
    """Each rest and each motion (with its attitude-path rows) predicted by the projected columns
    fitted to every other one, the nominal model's residual their target: a motion term (only
    the motion's own attitude path could copy it, and a held-out motion is whole), and the
    fallback. Every row of a rest or motion is judged, not only those the term acts on: the
    projection moves its evidence to the rows the nuisances share (the attitude path's)."""
    group = _row_groups(lin, paths=True)
    used = group >= 0
    _, g = np.unique(group[used], return_inverse=True)
    base = np.hstack([f.tested.projected for f in others]) if others else np.zeros((len(rp), 0))
    full = np.hstack([base, finding.tested.projected])
    before, after = np.zeros_like(rp), np.zeros_like(rp)
    (chi_b, before[used]), (chi_a, after[used]) = (_leave_one_out(X[used], rp[used], g) for X in (base, full))
    signal = (finding.tested.projected @ finding.theta)[used]  # the term as fitted to every row
    (sig_b, _), (sig_a, _) = (_leave_one_out(X[used], signal, g) for X in (base, full))
    n = used.sum()
    return _sensor_rms(lin, finding, before, after, (_gain_z(chi_b - chi_a, sig_b - sig_a), chi_b.sum() / n,
                                                     chi_a.sum() / n))


def _leave_one_out(X: np.ndarray, r: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of ``r`` on ``X`` with each group of rows (``g``: 0..G-1) left out in turn,
    in closed form: the group's predictive chi2 ``e_g' (I - H_gg)^-1 e_g`` (G,) and its residual
    predicted by the others' fit ``(I - H_gg)^-1 e_g`` (n,), from the fit to all (``e``,
    ``H = X (X'X)^-1 X'``) by Woodbury: ``(I - H_gg)^-1 = I + X_g (X'X - X_g'X_g)^-1 X_g'``."""
    G, k = int(g.max()) + 1, X.shape[1]
    if not k:
        return np.bincount(g, r * r, G), r.copy()
    e = r - X @ np.linalg.lstsq(X, r, rcond=None)[0]
    B_g = np.empty((G, k, k))
    for i in range(k):
        for j in range(i, k):
            B_g[:, i, j] = B_g[:, j, i] = np.bincount(g, X[:, i] * X[:, j], G)
    s = np.column_stack([np.bincount(g, X[:, i] * e, G) for i in range(k)])
    u = np.einsum("gkl,gl->gk", np.linalg.pinv(B_g.sum(0) - B_g, hermitian=True), s)
    return np.bincount(g, e * e, G) + np.einsum("gk,gk->g", s, u), e + np.einsum("nk,nk->n", X, u[g])

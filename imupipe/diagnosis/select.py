"""Name the physics a calibrated model leaves out, fit it, and check it on data it did not fit.

Each catalogue effect that offers ``regressors`` becomes a candidate: its term's whitened
columns ``C`` on the rows of the fitted per-sample model (``evaluate``): accelerometer
rest means and motion samples, gyro rest means. Everything the nominal model can already
do is projected off (``Cp = (I - P) C`` with ``P`` the projector on the calibration's and
the nuisances' Jacobian, through the fit's own block-tridiagonal system), so

- the **visible fraction** ``|Cp|^2 / |C|^2`` (smallest over the term's directions) says
  whether this recording can tell the effect from the nominal parameters at all; below
  ``VISIBLE_MIN`` it goes to ``not_identifiable`` with the parameters it would bias;
- the **score statistic** ``r' Cp (Cp' Cp)^-1 Cp' r`` is chi-square with the term's
  dimension under the null (scaled by the affected rows' chi2/dof when that exceeds 1,
  so an under-modelled noise floor does not pass for physics);
- **forward selection**: at each step every remaining candidate is tested conditionally on
  those accepted, Benjamini-Hochberg at ``q`` over them, the strongest significant one is
  accepted (its term refitted jointly with the others by the linearised Gauss-Newton step),
  then a backward check drops any accepted term that lost significance;
- **held-out proof**: by blocked cross-validation (5 folds of whole rests and whole
  motions) the term is fitted without a block and the block's residual RMS in the sensor's
  units is compared without and with it.

A p-value is the larger of the asymptotic (chi-square) one and a wild bootstrap's over 5-s
time blocks (``wild_p``: the recording's own noise, whatever its colour, without a noise
model); ``bench/diagnosis.py`` measures how often nulls produce a finding. Effects whose terms act through the attitude integration (gyro scale
asymmetry, saturation, g-sensitivity in motion), the magnetometer and the thermal lag are not
tested here yet: ``untested`` lists them with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.signal import savgol_filter

from ..effects.earth_rotation import EARTH_RATE
from ..rotations import skew
from .linearised import Linearised
from .residual_map import benjamini_hochberg

VISIBLE_MIN = 0.05
Q_FDR = 0.05
FOLDS = 5
WARMUP_TAUS_S = (30.0, 120.0, 600.0)
NONCENTRALITY_80 = 7.85  # chi2_1 noncentrality for 80 % power at alpha = 0.05
BLOCK_S = 5.0  # time blocks of the wild bootstrap (rows within a block keep their signs together)
BOOT_DRAWS = 999
UNTESTED = {
    "gyro_scale_asymmetry": "acts through the attitude integration inside motions (not in the score model yet)",
    "gyro_saturation": "acts through the attitude integration inside motions (not in the score model yet)",
    "gyro_scale_temperature": "acts through the attitude integration inside motions (not in the score model yet)",
    "thermal_lag": "needs a profiled lag of the temperature stream (not in the score model yet)",
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
    """What the candidates' regressors need, read once off the fitted model."""

    def __init__(self, lin: Linearised):
        model = lin.model
        self.lin, self.model = lin, model
        P = model.unpack(lin.x_g)
        self.S_a = P["S_a"]
        _, _, _, sig = model.residuals(lin.x_g, lin.x_l, signals=True, jacobian=False)
        g = model.g
        self.f_rest = g * sig["gravity_rest"]  # (n, 3) model frame
        self.T_rest = model.dT + 25.0
        self.rows_a, self.rows_g = _rows3(lin, "accel_rest"), _rows3(lin, "gyro_rest")
        self.W_a, self.W_g = model.W_a, model.W_g
        self.t_on_rest = model.mid - model.mid[0] + 0.5 * model.length[0]
        acc = model.accel
        self.rows_m = _rows3(lin, "accel_motion")
        self.has_motion = len(acc.t) > 0
        if self.has_motion:
            self.f_motion = g * sig["gravity_motion"]
            omega, _ = model._rates(P, lin.x_l, derivatives=False)
            ms = model.motions
            self.omega = np.zeros((len(acc.t), 3))
            self.alpha = np.zeros((len(acc.t), 3))
            self.f_dot = np.zeros((len(acc.t), 3))
            for j in np.unique(acc.motion):
                sel = acc.motion == j
                gs = ms.motion == j
                tj, wj = ms.t[gs], omega[gs]
                if len(tj) < 3 or sel.sum() < 3:
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


def _derivative(y: np.ndarray, t: np.ndarray, span_s: float = 0.1) -> np.ndarray:
    """d y / d t by a local cubic over ``span_s`` (Savitzky-Golay): differentiating raw noisy
    samples would put noise into the regressors and shrink the fitted term (errors in variables)."""
    dt = float(np.median(np.diff(t)))
    win = int(np.clip(round(span_s / dt) // 2 * 2 + 1, 5, len(t) // 2 * 2 - 1)) if len(t) >= 5 else 0
    if win < 5:
        return np.gradient(y, t, axis=0)
    return savgol_filter(y, win, 3, deriv=1, delta=dt, axis=0)


def candidates(lin: Linearised, frame: np.ndarray, registry) -> list[Candidate]:
    """The catalogue's terms this recording's rows can carry (``registry``: effects by identifier)."""
    s = Signals(lin)
    Q = frame
    out: list[Candidate] = []

    eff = registry
    if s.has_motion and "lever_arm" in eff:
        R = eff["lever_arm"].regressors({"omega": s.omega, "alpha": s.alpha})
        C = s.column(s.rows_m, s.model.W_sample, np.einsum("ij,njk->nik", s.S_a, R))
        out.append(Candidate("lever_arm", "accel", "motion", ["r_x", "r_y", "r_z"], C,
                             lambda th: {"r_m": list(Q.T @ th)}))
    if s.has_motion and "accel_gyro_time_offset" in eff:
        R = eff["accel_gyro_time_offset"].regressors({"f_dot": s.f_dot})
        C = s.column(s.rows_m, s.model.W_sample, np.einsum("ij,njk->nik", s.S_a, R))
        out.append(Candidate("accel_gyro_time_offset", "accel", "motion", ["dt_s"], C,
                             lambda th: {"dt_s": float(th[0])}))
    if "accel_nonlinearity" in eff:
        x_r = s.f_rest @ s.S_a.T
        C = s.column(s.rows_a, s.W_a, eff["accel_nonlinearity"].regressors({"x": x_r}))
        if s.has_motion:
            C = C + s.column(s.rows_m, s.model.W_sample,
                             eff["accel_nonlinearity"].regressors({"x": s.f_motion @ s.S_a.T}))
        out.append(Candidate("accel_nonlinearity", "accel", "all", ["k2_x", "k2_y", "k2_z"], C,
                             lambda th: {"k2": list(th)}))
    if "accel_scale_temperature" in eff:
        x_r = s.f_rest @ s.S_a.T
        C = s.column(s.rows_a, s.W_a, eff["accel_scale_temperature"].regressors({"x": x_r, "T": s.T_rest}))
        out.append(Candidate("accel_scale_temperature", "accel", "static", ["ppm_x", "ppm_y", "ppm_z"], C,
                             lambda th: {"ppm_per_C": list(th)}))
    if "bias_temperature_nonlinear" in eff:
        R = eff["bias_temperature_nonlinear"].regressors({"T": s.T_rest})
        for sensor, rows, W in (("accel", s.rows_a, s.W_a), ("gyro", s.rows_g, s.W_g)):
            out.append(Candidate("bias_temperature_nonlinear", sensor, "static", ["k2_x", "k2_y", "k2_z"],
                                 s.column(rows, W, R),
                                 lambda th, sensor=sensor: {"k2_per_C2": list(th), "sensor": sensor}))
    if "gyro_g_sensitivity" in eff:
        R = eff["gyro_g_sensitivity"].regressors({"f": s.f_rest})
        C = s.column(s.rows_g, s.W_g, R)
        out.append(Candidate("gyro_g_sensitivity", "gyro", "static", [f"G{i}{j}" for i in range(3) for j in range(3)],
                             C, lambda th: {"G": (th.reshape(3, 3) @ Q).tolist()}))
    if "earth_rotation" in eff:
        # at rest Earth's rate has a vertical part along gravity (Omega sin(lat), the same in every
        # rest: an isotropic g-sensitivity G = (Omega sin(lat) / g) I) and a horizontal part that
        # turns with the heading, which no rest fixes (left to the bias walk). One column, against
        # the nine of gyro_g_sensitivity: the selection names whichever explains the rests
        # with fewer parameters.
        up = s.f_rest / np.linalg.norm(s.f_rest, axis=1, keepdims=True)
        R = eff["earth_rotation"].regressors({"north": np.zeros_like(up), "up": up})[:, :, 1:]
        out.append(Candidate("earth_rotation", "gyro", "static", ["Omega_sin_lat"], s.column(s.rows_g, s.W_g, R),
                             _latitude))
    if "warmup_transient" in eff:
        for sensor, rows, W in (("accel", s.rows_a, s.W_a), ("gyro", s.rows_g, s.W_g)):
            for tau in WARMUP_TAUS_S:
                R = eff["warmup_transient"].regressors({"t_on": s.t_on_rest}, {"amp": [0, 0, 0], "tau_s": tau,
                                                                                "sensor": sensor})
                out.append(Candidate("warmup_transient", sensor, "warmup", ["amp_x", "amp_y", "amp_z"],
                                     s.column(rows, W, R),
                                     lambda th, sensor=sensor, tau=tau: {"amp": list(th), "tau_s": tau,
                                                                         "sensor": sensor},
                                     extra_dof=len(WARMUP_TAUS_S), fixed={"tau_s": tau}))
    return [c for c in out if np.any(c.columns)]


def _latitude(th: np.ndarray) -> dict:
    """Earth rate's vertical component (``Omega sin(lat)``) -> latitude (``diagnose`` renames a
    vertical rate beyond Earth's an isotropic gyro g-sensitivity)."""
    return {"latitude_deg": float(np.degrees(np.arcsin(np.clip(float(th[0]) / EARTH_RATE, -1, 1))))}


def project(lin: Linearised, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(I - P) C`` and the nominal globals' shift per unit of each column, ``z_g`` (P_g, k)."""
    return lin.project(C)


def examine(lin: Linearised, c: Candidate) -> Tested:
    Cp, z_g = project(lin, c.columns)
    A, B = c.columns.T @ c.columns, Cp.T @ Cp
    L = np.linalg.cholesky(A + 1e-300 * np.eye(len(A)))
    Li = np.linalg.inv(L)
    visible = float(np.clip(np.linalg.eigvalsh(Li @ B @ Li.T).min(), 0, 1))
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


def wild_p(Cp: np.ndarray, r: np.ndarray, groups: np.ndarray, draws: int = BOOT_DRAWS) -> float:
    """p-value of the score statistic ``r' Cp (Cp' Cp)^-1 Cp' r`` by a wild bootstrap over time
    blocks (``groups``: each row's block): every draw flips the sign of whole blocks of the
    residual. It keeps the recording's own noise -- correlated within a block, of any size and
    shape -- and needs no noise model; a term that is really there is consistent across blocks
    and stands out of the flipped draws. Deterministic (seeded)."""
    Binv = np.linalg.pinv(Cp.T @ Cp)
    _, inv = np.unique(groups, return_inverse=True)
    G = inv.max() + 1
    g_b = np.column_stack([np.bincount(inv, Cp[:, j] * r, G) for j in range(Cp.shape[1])])  # (G, k)
    g = g_b.sum(0)
    T = float(g @ Binv @ g)
    signs = np.random.default_rng(0).choice([-1.0, 1.0], (draws, G))
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


def select(lin: Linearised, tested: list[Tested], q: float = Q_FDR) -> tuple[np.ndarray, list[Finding]]:
    """Forward selection with BH at each step and a backward check; returns the residual
    with the nominal globals refitted (``rp``) and the accepted findings (theta fitted jointly)."""
    z_g, z_l = lin.system.solve(lin.J_g.T @ lin.r, lin.J_l.T @ lin.r)
    rp = lin.r - lin.J_g @ z_g - lin.J_l @ z_l  # the globals refitted too (Gauss-Newton step)
    n_rows = len(rp)
    pool = [t for t in tested if t.visible >= VISIBLE_MIN]
    accepted: list[Finding] = []

    t_rows = np.nan_to_num(lin.rows.t)
    groups = np.floor((t_rows - t_rows.min()) / BLOCK_S).astype(np.int64)

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
        p_asym = min(1.0, float(stats.chi2.sf(T, k)) * bonferroni)
        p = p_asym if p_asym > q else max(p_asym, min(1.0, wild_p(Cp, r, groups) * bonferroni))
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
    if accepted:
        A = np.hstack([f.tested.projected for f in accepted])
        theta = -np.linalg.lstsq(A, rp, rcond=None)[0]  # r(theta) = rp + A theta, minimised
        o = 0
        for f in accepted:
            k = f.tested.projected.shape[1]
            f.theta = theta[o:o + k]
            o += k
    return rp, accepted


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


def raw_units(lin: Linearised, r: np.ndarray) -> dict[str, np.ndarray]:
    """Un-whitened residual rows per sensor (accel rest + motion, gyro rest), sensor units,
    with each row's group id (rest ``i`` -> i, motion sample of motion ``j`` -> n + j)."""
    model = lin.model
    out = {}
    ra, rg, rm = _rows3(lin, "accel_rest"), _rows3(lin, "gyro_rest"), _rows3(lin, "accel_motion")
    n = model.n
    e_a = np.linalg.solve(model.W_a, r[ra][:, :, None])[:, :, 0]
    e_m = np.linalg.solve(model.W_sample, r[rm].T).T if len(rm) else np.zeros((0, 3))
    out["accel"] = (np.vstack([e_a, e_m]), np.r_[np.arange(n), n + model.accel.motion])
    out["gyro"] = (np.linalg.solve(model.W_g, r[rg][:, :, None])[:, :, 0], np.arange(n))
    return out


def heldout(lin: Linearised, rp: np.ndarray, finding: Finding, others: list[Finding]) -> tuple[float, float]:
    """Blocked cross-validated RMS (sensor units) of the finding's sensor rows without and with
    its term (others already accepted are in both): folds of whole rests and motions."""
    model = lin.model
    groups = np.full(len(rp), -1)
    for name in ("accel_rest", "gyro_rest"):
        rows = _rows3(lin, name)
        groups[rows] = np.arange(len(rows))[:, None]
    rm = _rows3(lin, "accel_motion")
    if len(rm):
        groups[rm] = (model.n + model.accel.motion)[:, None]
    fold = np.where(groups >= 0, (groups * 7919) % FOLDS, -1)
    base = np.hstack([f.tested.projected for f in others]) if others else np.zeros((len(rp), 0))
    full = np.hstack([base, finding.tested.projected])
    before, after = np.zeros_like(rp), np.zeros_like(rp)
    for k in range(FOLDS):
        train, test = (fold != k) & (fold >= 0), fold == k
        for X, out in ((base, before), (full, after)):
            theta = np.linalg.lstsq(X[train], rp[train], rcond=None)[0] if X.shape[1] else np.zeros(0)
            out[test] = rp[test] - X[test] @ theta
    sensor = finding.tested.candidate.sensor
    rows = np.any(finding.tested.candidate.columns != 0, axis=1)
    e0, g0 = raw_units(lin, np.where(rows, before, 0))[sensor]
    e1, _ = raw_units(lin, np.where(rows, after, 0))[sensor]
    used = np.any(e0 != 0, axis=1)
    rms = lambda e: float(np.sqrt(np.mean(e[used] ** 2))) if used.any() else float("nan")  # noqa: E731
    return rms(e0), rms(e1)

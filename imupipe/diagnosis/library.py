"""Structure cells: does a sensor's misfit in a regime follow the motion, gravity or temperature?

A chi2/dof cell compares the residual energy of many rows with their count, so a term
worth a few hundred of chi2 spread over 1e5 motion samples is invisible there (its
excess is below the noise of the count, sqrt(2 dof)). A structure cell asks a narrower
question of the same rows: is the whitened residual correlated with a small, generic
library of smooth signals of what the model already reconstructs (per output axis:
products of the rates, angular acceleration and the rate of change of specific force
in motion; products of the specific force, temperature terms and a warm-up
exponential at rest; the specific force for the gyro at rest)? The library is
whitened like the residual and projected off the nominal Jacobian (calibration and
every nuisance: what the model can already do), directions less than
``VISIBLE_MIN`` visible are dropped, and the score statistic ``r' P_L r`` is chi-square
with the kept directions' count under the null. Its noncentrality is what a fitted
term would remove, so a structure cell sees an effect near the catalogue tests'
detection limit, names its sensor, axis and regime, and says which signals it follows
(the library terms with the largest t) -- the catalogue is not consulted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2 as chi2_dist

from .linearised import Linearised
from .residual_map import windows
from .select import BOOT_DRAWS, Q_FDR, VISIBLE_MIN, Signals, time_blocks, wild_p

AXES = ("x", "y", "z")
WARMUP_TAU_S = 120.0
_PAIRS = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]


@dataclass(frozen=True)
class StructureCell:
    """A map cell (``residual_map.Cell``'s face) whose statistic is the library's score test:
    ``chi2`` the statistic (scaled by the rows' chi2/dof when that exceeds 1), ``dof`` the
    library directions tested; ``terms`` the strongest library signals with coefficient and t."""

    sensor: str
    axes: tuple[str, ...]
    regime: str
    chi2: float
    dof: float
    windows: list[tuple[float, float]]
    terms: list[dict] = field(default_factory=list)
    variable: str = "structure"
    lo: float = -np.inf
    hi: float = np.inf
    p_bootstrap: float = 0.0  # the wild bootstrap's p (``structure_cells(bootstrap=True)``), else 0

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def p_value(self) -> float:
        return max(float(chi2_dist.sf(self.chi2, self.dof)), self.p_bootstrap)


@dataclass
class _Library:
    sensor: str
    regime: str
    rows: np.ndarray  # (n, 3) rows of the fit
    W: np.ndarray  # (3, 3) or (n, 3, 3) whitener of those rows
    columns: list[tuple[int, str, np.ndarray, str]]  # (output axis, name, regressor (n,), unit)


def libraries(s: Signals) -> list[_Library]:
    out = []
    dT, f_r = s.model.dT, s.f_rest
    warm = np.exp(-s.t_on_rest / WARMUP_TAU_S)
    static_a, static_g = [], []
    for i in range(3):
        static_a += [(i, f"f_{AXES[j]}*f_{AXES[k]}", f_r[:, j] * f_r[:, k], "(m/s^2)^2") for j, k in _PAIRS]
        static_a += [(i, f"f_{AXES[j]}*dT", f_r[:, j] * dT, "m/s^2 degC") for j in range(3)]
        static_a += [(i, "dT^2", dT ** 2, "degC^2"), (i, f"exp(-t_on/{WARMUP_TAU_S:g} s)", warm, "1")]
        static_g += [(i, f"f_{AXES[j]}", f_r[:, j], "m/s^2") for j in range(3)]
        static_g += [(i, "dT^2", dT ** 2, "degC^2"), (i, f"exp(-t_on/{WARMUP_TAU_S:g} s)", warm, "1")]
    out.append(_Library("accel", "static", s.rows_a, s.W_a, static_a))
    out.append(_Library("gyro", "static", s.rows_g, s.W_g, static_g))
    if s.has_motion and len(s.rows_m):
        w, a, fd, f = s.omega, s.alpha, s.f_dot, s.f_motion
        motion = []
        for i in range(3):
            motion += [(i, f"w_{AXES[j]}*w_{AXES[k]}", w[:, j] * w[:, k], "(rad/s)^2") for j, k in _PAIRS]
            motion += [(i, f"alpha_{AXES[j]}", a[:, j], "rad/s^2") for j in range(3)]
            motion += [(i, f"fdot_{AXES[j]}", fd[:, j], "m/s^3") for j in range(3)]
            motion += [(i, f"f_{AXES[j]}*f_{AXES[k]}", f[:, j] * f[:, k], "(m/s^2)^2") for j, k in _PAIRS]
        out.append(_Library("accel", "motion", s.rows_m, s.model.W_sample, motion))
    return [lib for lib in out if len(lib.rows)]


def bootstrap_draws(tests: int, level: float) -> int:
    """Wild-bootstrap draws whose smallest p (1 / (draws + 1)) is at most half the
    Benjamini-Hochberg threshold of the strongest of ``tests`` at ``level``: the bootstrap's
    floor never decides a discovery."""
    return max(BOOT_DRAWS, int(np.ceil(2 * tests / level)) - 1)


def structure_cells(lin: Linearised, given: np.ndarray | None = None, r: np.ndarray | None = None,
                    unit: dict[str, str] | None = None, bootstrap: bool = False,
                    level: float = Q_FDR) -> list[StructureCell]:
    """One cell per sensor x regime of the library (all axes) and per output axis. With ``given``
    (N, m) columns already projected off the nominal Jacobian (accepted terms) and the residual
    ``r`` they were selected on, the test is conditional on those terms being fitted too.
    ``bootstrap``: each p-value is also the wild bootstrap's (``select.wild_p``; the projected
    library is then formed on every row, with ``bootstrap_draws`` for the cells' Benjamini-Hochberg
    ``level``), as the diagnosis asks of a named finding."""
    s = Signals(lin)
    unit = unit or {"accel": "m/s^2", "gyro": "rad/s"}
    r = lin.r if r is None else r
    Jr_g, Jr_l = lin.J_g.T @ r, lin.J_l.T @ r  # ~0 at the optimum; kept for exactness
    if given is not None and given.shape[1]:
        AA_inv = np.linalg.pinv(given.T @ given)
        theta_given = -AA_inv @ (given.T @ r)
        r_after = r + given @ theta_given
    out = []
    libs = libraries(s)
    draws = bootstrap_draws(len(libs) * (1 + len(AXES)), level)
    for lib in libs:
        n = len(lib.rows)
        # d r / d theta on the library's rows: column c moves raw axis i only, so it is the
        # whitener's column i times the regressor (no (n, 3, k) raw-derivative array)
        C = np.empty((n, 3, len(lib.columns)))
        for c, (i, _, x, _) in enumerate(lib.columns):
            C[:, :, c] = -(lib.W[..., :, i] * x[:, None])
        C = C.reshape(3 * n, -1)
        rows = lib.rows.ravel()
        # the rows of a block are contiguous: a slice is a view of J_g, an index list a copy
        at = slice(rows[0], rows[-1] + 1) if len(rows) and rows[-1] - rows[0] + 1 == len(rows) and \
            np.all(np.diff(rows) == 1) else rows
        JgC, JlC = lin.J_g[at].T @ C, np.asarray(lin.J_l[at].T @ C)
        z_g, z_l = lin.system.solve(JgC, JlC)
        # C'(I - P)C and C'(I - P)r without forming (I - P)C, which would fill every row
        gram = C.T @ C
        proj = gram - JgC.T @ z_g - JlC.T @ z_l
        h = C.T @ r[rows] - z_g.T @ Jr_g - z_l.T @ Jr_l
        r_rows = r[rows]
        if given is not None and given.shape[1]:
            LA = C.T @ given[rows]  # = ((I - P)C)' given, as given is already off the Jacobian
            proj = proj - LA @ AA_inv @ LA.T
            h = h + LA @ theta_given
            r_rows = r_after[rows]
        lev = lin.leverage[rows] if lin.leverage is not None else np.zeros(len(rows))
        scale = max(1.0, float(r_rows @ r_rows) / max(float(np.sum(1 - lev)), 1.0))
        t_rows = lin.rows.t[rows]
        boot = None
        if bootstrap:
            Cp = -(lin.J_g @ z_g) - lin.J_l @ z_l  # (I - P) C on every row
            Cp[rows] += C
            r_boot = r
            if given is not None and given.shape[1]:
                Cp -= given @ (AA_inv @ LA.T)
                r_boot = r_after
            boot = (Cp, r_boot, time_blocks(lin), draws)
        for axes in [tuple(AXES)] + [(a,) for a in AXES]:
            sel = np.array([AXES[i] in axes for i, *_ in lib.columns])
            cell = _score(lib, axes, sel, gram, proj, h, scale, C, t_rows, unit[lib.sensor], boot)
            if cell is not None:
                out.append(cell)
    return out


def _score(lib: _Library, axes, sel, gram, proj, h, scale, C, t_rows, unit, boot=None) -> StructureCell | None:
    idx = np.flatnonzero(sel & (np.diag(gram) > 0))
    if not len(idx):
        return None
    d = np.sqrt(np.diag(gram)[idx])
    A = gram[np.ix_(idx, idx)] / np.outer(d, d)
    B = proj[np.ix_(idx, idx)] / np.outer(d, d)
    hn = h[idx] / d
    lam, V = np.linalg.eigh(A)  # an orthonormal basis of the library's span
    keep = lam > 1e-10 * lam.max()
    T = V[:, keep] / np.sqrt(lam[keep])
    vis, U = np.linalg.eigh(T.T @ B @ T)  # visible fraction of each direction of that span
    ok = vis >= VISIBLE_MIN
    if not ok.any():
        return None
    D = T @ U[:, ok]  # directions (normalised column coordinates) the model cannot make
    score = D.T @ hn
    stat = float(np.sum(score ** 2 / vis[ok]))
    theta = -D @ (score / vis[ok])  # the fitted library term (normalised coordinates)
    w = np.zeros(C.shape[1])
    w[idx] = theta / d
    contrib = (C @ w) ** 2  # (no copy of the selected columns)
    # the signals the structure follows: marginal t of each projected column, largest first
    bjj = np.diag(B)
    shown = bjj >= VISIBLE_MIN  # a column the nominal model absorbs has no t of its own
    t = np.where(shown, hn / np.sqrt(np.where(shown, bjj, 1.0)), 0.0)
    terms = []
    for j in [j for j in np.argsort(-np.abs(t)) if shown[j]][:3]:
        i, name, _, ru = lib.columns[idx[j]]
        coef = -h[idx[j]] / (bjj[j] * d[j] ** 2)
        terms.append({"output_axis": AXES[i], "signal": name, "coefficient": float(coef),
                      "unit": f"{unit} per {ru}", "t": float(t[j])})
    p_boot = 0.0
    if boot is not None:
        Cp, r_boot, groups, draws = boot
        p_boot = wild_p(Cp[:, idx] @ (D / d[:, None]), r_boot, groups, draws)
    return StructureCell(lib.sensor, axes, lib.regime, stat / scale, float(ok.sum()),
                         windows(t_rows, contrib), terms, p_bootstrap=p_boot)

"""Structure cells: does a sensor's misfit in a regime follow the motion, gravity or temperature?

A chi2/dof cell compares the residual energy of many rows with their count, so a term
worth a few hundred of chi2 spread over 1e5 motion samples is invisible there (its
excess is below the noise of the count, sqrt(2 dof)). A structure cell asks a narrower
question of the same rows: is the whitened residual correlated with a small, generic
library of smooth signals of what the model already reconstructs (per output axis:
products of the rates, angular acceleration and the rate of change of specific force
for the accelerometer in motion, the magnitude of each sensed rate for the gyro in
motion; static terms on every reading, as a catalogue term acts: products of the
specific force, temperature terms and a warm-up exponential for the accelerometer, the
specific force, temperature squared and the warm-up for the gyro; the gyro's terms reach
the motions through the attitude)? The library is
whitened like the residual and projected off the nominal Jacobian (calibration and
every nuisance: what the model can already do), directions the nominal parameters leave
less than ``VISIBLE_MIN`` visible (the bias walks held still, as for a catalogue term) are
dropped, and the score statistic ``r' P_L r`` (the walks free) is chi-square with the kept
directions' count under the null. Its noncentrality is what a fitted
term would remove, so a structure cell sees an effect near the catalogue tests'
detection limit, names its sensor, axis and regime, and says which signals it follows
(the library terms with the largest t) -- the catalogue is not consulted. With the wild
bootstrap's block scores (the diagnosis), a cell also says which signals a sparse fit keeps
consistently (``_stable_terms``: noise-calibrated forward selection on random halves of the
recording, stability selection): the marginal t's of correlated signals (f_x^2 and f_y^2
at rest, whose sum is g^2) name several where one acts.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from .. import tails
from .attitude import RateDerivatives
from .forward import GyroColumns
from .linearised import Linearised
from .residual_map import strongest, window_starts
from .select import BOOT_DRAWS, Q_FDR, VISIBLE_MIN, Signals, block_wild_p, rigid_solver, time_blocks

AXES = ("x", "y", "z")
WARMUP_TAU_S = 120.0
CHUNK = 8192  # readings whose library columns are formed at once
INFO_MIN = 1e-6  # a direction with less of its information left than this is not tested (numerically nil)
STABLE_HALVES = 100  # random halves of the time blocks in the stability selection
STABLE_MIN = 0.6  # share of the halves whose sparse fit must choose a signal for it to be stable
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
    stable: list[dict] = field(default_factory=list)  # ``_stable_terms`` (with the bootstrap's block scores)

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def p_value(self) -> float:
        return max(float(tails.chi2_sf(self.chi2, self.dof)), self.p_bootstrap)


@dataclass
class _Readings:
    """Rows whose readings a library's regressors act on directly (rest means, motion samples):
    column ``c`` adds ``X(sl)[:, c]`` to raw axis ``axis[c]``, whitened by ``W`` ((3, 3) or (n, 3, 3)).
    ``X(sl)``: the library's signals at a slice of the readings, formed as they are read."""

    rows: np.ndarray  # (n, 3) rows of the fit
    W: np.ndarray
    X: Callable[[slice], np.ndarray]  # -> (len(sl), u): column c uses signal use[c]

    def __len__(self) -> int:
        return len(self.rows)

    def form(self, sl: slice, axis: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        W = self.W if self.W.ndim == 2 else self.W[sl]
        C = -(W[..., :, axis] * self.X(sl)[:, None, use])  # d r / d theta: whitener column times regressor
        return self.rows[sl].ravel(), C.reshape(-1, len(axis))


@dataclass
class _Carried:
    """Motion rows a gyro term reaches through the integrated attitude. A slow signal is its mean
    over a motion's few seconds there, a constant gyro bias: its column on those rows is the
    bias's Jacobian column (``J_g``'s ``b_g`` columns on those rows) times that mean (``means``
    (motions, u), zero for the exact signals, at each row's ``motion``). A signal that changes
    within a motion (the specific force, turning with the attitude) has its exact columns
    ``exact`` in ``E`` (m, len(exact)) (``Signals.gyro_motion_column``), formed by slices of rows
    as they are read (``forward.GyroColumns``): nothing here is as long as the rows."""

    rows: np.ndarray  # (m,)
    J_g: np.ndarray
    b_g: slice
    motion: np.ndarray  # (m,)
    means: np.ndarray
    E: GyroColumns
    exact: list[int]

    def __len__(self) -> int:
        return len(self.rows)

    def form(self, sl: slice, axis: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows = self.rows[sl]
        C = self.J_g[rows, self.b_g][:, axis] * self.means[self.motion[sl]][:, use]
        C[:, self.exact] += self.E[sl]
        return rows, C


@dataclass
class _Library:
    """A library's columns on the rows of the fit; its ``parts`` (``_Readings`` / ``_Carried`` on
    disjoint rows, as long as the recording) are formed on first use and dropped by ``forget``:
    the structure cells hold one library's at a time."""

    sensor: str
    regime: str
    columns: list[tuple[int, str, str, int]]  # (output axis, name, unit, signal index)
    make: Callable[[], list]  # its parts
    readings: int  # the rows its parts cover

    @cached_property
    def parts(self) -> list:
        return self.make()

    def forget(self) -> None:
        self.__dict__.pop("parts", None)

    def chunks(self):
        """(rows, C) pieces of the whitened columns, ``CHUNK`` readings at a time: never all rows."""
        axis = np.array([c[0] for c in self.columns])
        use = np.array([c[3] for c in self.columns])
        for part in self.parts:
            for a in range(0, len(part), CHUNK):
                yield part.form(slice(a, a + CHUNK), axis, use)


def _static(f: np.ndarray, dT: np.ndarray, warm: np.ndarray, gyro: bool) -> list[tuple[str, np.ndarray, str]]:
    """(name, regressor, unit) of a triad's static library at some readings: products of the
    specific force and temperature terms (accelerometer) or the specific force (gyro), the
    temperature squared and a warm-up exponential."""
    if gyro:
        out = [(f"f_{AXES[j]}", f[:, j], "m/s^2") for j in range(3)]
    else:
        out = [(f"f_{AXES[j]}*f_{AXES[k]}", f[:, j] * f[:, k], "(m/s^2)^2") for j, k in _PAIRS]
        out += [(f"f_{AXES[j]}*dT", f[:, j] * dT, "m/s^2 degC") for j in range(3)]
    return out + [("dT^2", dT ** 2, "degC^2"), (f"exp(-t_on/{WARMUP_TAU_S:g} s)", warm, "1")]


def _per_axis(signals: list) -> list[tuple[int, str, str, int]]:
    """Every signal on every output axis: (axis, name, unit, signal index)."""
    return [(i, name, unit, u) for i in range(3) for u, (name, _, unit) in enumerate(signals)]


def _matrix(signals: list) -> np.ndarray:
    return np.column_stack([x for _, x, _ in signals])


def libraries(s: Signals) -> list[_Library]:
    """The static libraries act on every reading, as the catalogue's terms do (a slow term left out
    of the motions is one the bias walk copies at the rests for free): the accelerometer's on its
    rest means and motion samples, the gyro's on its rest means and through the motions'
    attitude (``_Carried``). Their parts are formed when first read."""
    model = s.model
    warm = lambda t_on: np.exp(-t_on / WARMUP_TAU_S)  # noqa: E731
    motion_a = s.has_motion and len(s.rows_m)
    carried = len(model.motion_rows) if s.has_gyro_motion else 0
    rest_a = _static(s.f_rest, model.dT, warm(s.t_on_rest), gyro=False)
    rest_g = _static(s.f_rest, model.dT, warm(s.t_on_rest), gyro=True)

    def accel_static() -> list:
        parts = [_Readings(s.rows_a, s.W_a, _matrix(rest_a).__getitem__)]
        if motion_a:
            parts.append(_Readings(s.rows_m, model.W_sample, lambda sl: _matrix(_static(
                s.f_motion[sl], model.dT_acc[sl], warm(s.t_on_motion[sl]), gyro=False))))
        return parts

    def gyro_static() -> list:
        parts = [_Readings(s.rows_g, s.W_g, _matrix(rest_g).__getitem__)]
        if carried:
            motion = _static(s.f_gyro_motion, model.dT_gyro, warm(s.t_on_gyro_motion), gyro=True)
            parts.append(_carried(s, motion, [name.startswith("f_") for name, _, _ in motion]))
        return parts

    out = [_Library("accel", "static", _per_axis(rest_a), accel_static,
                    len(s.rows_a) + (len(s.rows_m) if motion_a else 0)),
           _Library("gyro", "static", _per_axis(rest_g), gyro_static, len(s.rows_g) + carried)]
    if carried:  # a response that differs with the rate's sign (scale asymmetry, rectification)
        out.append(_Library("gyro", "motion", _per_axis(_abs_rate(s, slice(0, 0))),
                            lambda: [_carried(s, _abs_rate(s, slice(None)), [True] * 3)], carried))
    if motion_a:  # its names read here (of no samples), its signals formed by slices as they are read
        out.append(_Library("accel", "motion", _per_axis(_accel_motion(s, slice(0, 0))),
                            lambda: [_Readings(s.rows_m, model.W_sample, lambda sl: _matrix(_accel_motion(s, sl)))],
                            len(s.rows_m)))
    return [lib for lib in out if lib.readings]


def _abs_rate(s: Signals, sl: slice) -> list[tuple[str, np.ndarray, str]]:
    """The gyro's motion library at its motion samples ``sl``: the magnitude of each sensed rate."""
    return [(f"|x_{AXES[j]}|", np.abs(s.x_gyro_motion[sl, j]), "rad/s") for j in range(3)]


def _accel_motion(s: Signals, sl: slice) -> list[tuple[str, np.ndarray, str]]:
    """The accelerometer's motion library at motion samples ``sl``: rate products, angular
    acceleration, jerk of the specific force and its products."""
    w, a, fd, f = s.omega[sl], s.alpha[sl], s.f_dot[sl], s.f_motion[sl]
    out = [(f"w_{AXES[j]}*w_{AXES[k]}", w[:, j] * w[:, k], "(rad/s)^2") for j, k in _PAIRS]
    out += [(f"alpha_{AXES[j]}", a[:, j], "rad/s^2") for j in range(3)]
    out += [(f"fdot_{AXES[j]}", fd[:, j], "m/s^3") for j in range(3)]
    return out + [(f"f_{AXES[j]}*f_{AXES[k]}", f[:, j] * f[:, k], "(m/s^2)^2") for j, k in _PAIRS]


def _carried(s: Signals, signals: list, exact: list[bool]) -> _Carried:
    """A gyro library carried into the motions' rows (``_Carried``): the slow signals (temperature,
    warm-up) by each motion's mean at its gyro samples times the gyro bias's columns, the
    ``exact`` ones (changing within a motion: the specific force, the rate) by their own columns."""
    lin, model = s.lin, s.model
    ms, rows = model.motions, lin.rows
    turn, acc = np.flatnonzero(rows.of("turn")), np.flatnonzero(rows.of("accel_motion"))
    at = np.r_[turn, acc]  # = model.motion_rows, the rows of its gyro columns
    motion = np.r_[rows.index[turn], model.accel.motion[rows.index[acc]]] if len(acc) else rows.index[turn]
    count = np.maximum(np.bincount(ms.motion, minlength=ms.count), 1)
    means = np.zeros((ms.count, len(signals)))
    for u, (_, x, _) in enumerate(signals):
        if not exact[u]:
            means[:, u] = np.bincount(ms.motion, x, ms.count) / count
    columns = _per_axis(signals)
    by_column = [c for c, (_, _, _, u) in enumerate(columns) if exact[u]]
    used = sorted({columns[c][3] for c in by_column})
    basis = np.zeros((len(used), 3, len(by_column)))  # each column: one signal on one axis
    for j, c in enumerate(by_column):
        i, _, _, u = columns[c]
        basis[used.index(u), i, j] = 1.0
    coef = np.column_stack([signals[u][1] for u in used]) if used else np.zeros((len(ms.t), 0))
    dy = RateDerivatives(coef, basis)
    return _Carried(at, lin.J_g, lin.globals.slices["b_g"], motion, means, s.gyro_motion_column(dy, by_rows=True),
                    by_column)


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
    ``bootstrap``: each p-value is also the wild bootstrap's (``select.block_wild_p``, with
    ``bootstrap_draws`` for the cells' Benjamini-Hochberg ``level``), as the diagnosis asks of a
    named finding. Every statistic is a sum over rows, accumulated over chunks of the library's
    columns (``_Library.chunks``)."""
    s = Signals(lin)
    unit = unit or {"accel": "m/s^2", "gyro": "rad/s"}
    r = lin.r if r is None else r
    N = len(r)
    Jr_g, Jr_l = lin.J_g.T @ r, lin.J_l.T @ r  # ~0 at the optimum; kept for exactness
    conditional = given is not None and given.shape[1] > 0
    if conditional:
        AA_inv = np.linalg.pinv(given.T @ given)
        theta_given = -AA_inv @ (given.T @ r)
        r_after = r + given @ theta_given
    r_use = r_after if conditional else r
    lev = lin.leverage if lin.leverage is not None else np.zeros(N)
    if bootstrap:  # each time block's sums of r-weighted rows: the block scores of the projected columns
        _, blocks = np.unique(time_blocks(lin), return_inverse=True)
        Gr = sp.csc_matrix((r_use, (blocks, np.arange(N))), shape=(blocks.max() + 1, N))  # sliced by rows of the fit
        S_g, S_l = Gr @ lin.J_g, Gr @ lin.J_l
    libs = libraries(s)  # each formed in turn below, then forgotten: one library's columns held at a time
    rigid = rigid_solver(lin)
    out = []
    draws = bootstrap_draws(len(libs) * (1 + len(AXES)), level)
    for lib in libs:
        k = len(lib.columns)
        gram, Cr = np.zeros((k, k)), np.zeros(k)
        JgC, JlC = np.zeros((lin.J_g.shape[1], k)), np.zeros((lin.J_l.shape[1], k))
        LA = np.zeros((k, given.shape[1])) if conditional else None
        GB = np.zeros((Gr.shape[0], k)) if bootstrap else None
        rr = dof = 0.0
        near = _Windows(lin, lib)
        for rows, C in lib.chunks():
            rows = _as_slice(rows)
            near.add(C)
            gram += C.T @ C
            JgC += lin.J_g[rows].T @ C
            JlC += lin.J_l[rows].T @ C
            Cr += C.T @ r[rows]
            rr += float(r_use[rows] @ r_use[rows])
            dof += float(np.sum(1 - lev[rows]))
            if conditional:
                LA += C.T @ given[rows]  # = ((I - P)C)' given, as given is already off the Jacobian
            if bootstrap:
                GB += Gr[:, rows] @ C
        z_g, z_l = lin.system.solve(JgC, JlC)
        # C'(I - P)C and C'(I - P)r without forming (I - P)C, which would fill every row
        proj = gram - JgC.T @ z_g - JlC.T @ z_l
        h = Cr - z_g.T @ Jr_g - z_l.T @ Jr_l
        g_b = None
        if bootstrap:  # block sums of (I - P) C (minus the given terms' share) times r
            g_b = GB - S_g @ z_g - np.asarray(S_l @ z_l)
            if conditional:
                g_b -= (Gr @ given) @ (AA_inv @ LA.T)
        del z_g, z_l  # (P_l, k): let go before the next solve forms its own, the cells' peak
        # what the nominal parameters alone leave visible: the walks held still (the columns are
        # zero on the walks' rows, so only the system differs)
        v_g, v_l = rigid.solve(JgC, JlC)
        visible = gram - JgC.T @ v_g - JlC.T @ v_l
        del v_g, v_l
        if conditional:
            proj = proj - LA @ AA_inv @ LA.T
            h = h + LA @ theta_given
        scale = max(1.0, rr / max(dof, 1.0))
        scored = []
        for axes in [tuple(AXES)] + [(a,) for a in AXES]:
            sel = np.array([AXES[i] in axes for i, *_ in lib.columns])
            cell = _score(lib, axes, sel, gram, visible, proj, h, scale, unit[lib.sensor], g_b, draws)
            if cell is not None:
                scored.append(cell)
        out += near.placed(scored)
        lib.forget()
    return out


def _as_slice(rows: np.ndarray) -> slice | np.ndarray:
    """``rows`` as the slice it spans when it is one ascending run (a library's readings mostly
    are): a slice of J_l copies one stretch of its arrays and a slice of J_g is a view, where
    indexing by the rows gathers them one at a time (the same values either way)."""
    n = len(rows)
    if n and rows[-1] - rows[0] == n - 1 and np.all(rows[1:] - rows[:-1] == 1):
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


def _score(lib: _Library, axes, sel, gram, visible, proj, h, scale, unit, g_b=None, draws: int = BOOT_DRAWS
           ) -> tuple[StructureCell, np.ndarray] | None:
    """The cell's score test and its fitted library term ``w`` (k,), raw column coordinates. The
    directions tested are those the nominal parameters leave ``VISIBLE_MIN`` visible (``visible``:
    C'(I - P)C with the bias walks held still, as a catalogue term's visible fraction); the test
    uses the information left with the walks free (``proj``): a slow term the walks could copy
    is still tested, with the power that leaves (``select``'s candidates do the same)."""
    idx = np.flatnonzero(sel & (np.diag(gram) > 0))
    if not len(idx):
        return None
    d = np.sqrt(np.diag(gram)[idx])
    norm = np.outer(d, d)
    A, Bv, B = gram[np.ix_(idx, idx)] / norm, visible[np.ix_(idx, idx)] / norm, proj[np.ix_(idx, idx)] / norm
    hn = h[idx] / d
    lam, V = np.linalg.eigh(A)  # an orthonormal basis of the library's span
    keep = lam > 1e-10 * lam.max()
    T = V[:, keep] / np.sqrt(lam[keep])
    vis, U = np.linalg.eigh(T.T @ Bv @ T)  # visible fraction of each direction of that span
    ok = vis >= VISIBLE_MIN ** 2  # an information ratio; the visible fraction is its square root
    if not ok.any():
        return None
    info, E = np.linalg.eigh(U[:, ok].T @ (T.T @ B @ T) @ U[:, ok])  # the same directions, walks free
    good = info > INFO_MIN
    if not good.any():
        return None
    D = T @ U[:, ok] @ E[:, good]  # directions (normalised column coordinates) tested
    score = D.T @ hn
    stat = float(np.sum(score ** 2 / info[good]))
    theta = -D @ (score / info[good])  # the fitted library term (normalised coordinates)
    w = np.zeros(len(lib.columns))
    w[idx] = theta / d
    # the signals the structure follows: marginal t of each projected column, largest first
    bjj = np.diag(B)
    shown = (np.diag(Bv) >= VISIBLE_MIN ** 2) & (bjj > INFO_MIN)  # a column the model absorbs has no t of its own
    t = np.where(shown, hn / np.sqrt(np.where(shown, bjj, 1.0)), 0.0)
    terms = []
    for j in [j for j in np.argsort(-np.abs(t)) if shown[j]][:3]:
        terms.append(_term(lib, idx[j], -h[idx[j]] / (bjj[j] * d[j] ** 2), t[j], unit))
    p_boot, stable = 0.0, []
    if g_b is not None:
        M = D / d[:, None]  # the tested directions in raw column coordinates
        p_boot = block_wild_p(g_b[:, idx] @ M, M.T @ proj[np.ix_(idx, idx)] @ M, draws)
        sub = np.flatnonzero(shown)
        stable = [{**_term(lib, idx[sub[j]], coef / d[sub[j]], t, unit), "chosen": share}
                  for j, coef, t, share in _stable_terms(B[np.ix_(sub, sub)], hn[sub], g_b[:, idx[sub]] / d[sub])]
    return StructureCell(lib.sensor, axes, lib.regime, stat / scale, float(good.sum()), [], terms,
                         p_bootstrap=p_boot, stable=stable), w


def _term(lib: _Library, column: int, coefficient: float, t: float, unit: str) -> dict:
    i, name, ru, _ = lib.columns[column]
    return {"output_axis": AXES[i], "signal": name, "coefficient": float(coefficient), "unit": f"{unit} per {ru}",
            "t": float(t)}


def _sparse(B: np.ndarray, h: np.ndarray, t2_min: float) -> list[int]:
    """Forward selection of library columns from their projected information ``B`` and score
    ``h`` (normalised columns): each step adds the column whose score, conditional on those
    chosen, has the largest t^2, while that exceeds ``t2_min``. The whitened score's noise is
    N(0, B), so the threshold is calibrated by the noise itself."""
    chosen: list[int] = []
    while len(chosen) < len(h):
        P = np.linalg.solve(B[np.ix_(chosen, chosen)], B[chosen]).T if chosen else np.zeros((len(h), 0))
        hc, bc = h - P @ h[chosen], np.diag(B) - np.sum(P * B[:, chosen], axis=1)
        t2 = np.where(bc > INFO_MIN, hc ** 2 / np.maximum(bc, INFO_MIN), 0.0)
        t2[chosen] = 0.0
        j = int(np.argmax(t2))
        if t2[j] <= t2_min:
            break
        chosen.append(j)
    return chosen


def _stable_terms(B: np.ndarray, h: np.ndarray, g_b: np.ndarray) -> list[tuple[int, float, float, float]]:
    """Stability selection (Meinshausen and Buehlmann): ``_sparse`` (Bonferroni over the columns
    at ``Q_FDR``) on ``STABLE_HALVES`` random halves of the time blocks (``g_b`` (G, m): each
    block's score; a half has about half the information), and the columns chosen in at least
    ``STABLE_MIN`` of them, most often chosen first: ``(column, coefficient, t, share)`` with
    the coefficient (normalised column) and t of their joint fit to all the data."""
    t2_min = float(tails.chi2_isf(Q_FDR / len(h), 1))
    rng = np.random.default_rng(0)
    counts = np.zeros(len(h))
    for _ in range(STABLE_HALVES):
        half = rng.permutation(len(g_b))[:len(g_b) // 2]
        counts[_sparse(B / 2, g_b[half].sum(0), t2_min)] += 1
    share = counts / STABLE_HALVES
    keep = np.flatnonzero(share >= STABLE_MIN)
    keep = keep[np.argsort(-share[keep], kind="stable")]
    if not len(keep):
        return []
    cov = np.linalg.pinv(B[np.ix_(keep, keep)])
    score = cov @ h[keep]
    t = score / np.sqrt(np.maximum(np.diag(cov), INFO_MIN))
    return [(int(j), float(-score[n]), float(t[n]), float(share[j])) for n, j in enumerate(keep)]


class _Windows:
    """A library's rows grouped into ``residual_map.windows``' time windows (its rows' times
    joined across gaps < 2 s), each window's ``C'C`` summed as the chunks pass (``add``, in the
    chunks' order): a scored cell's fitted term ``C w`` puts ``w' (C'C) w`` of excess in each,
    and ``placed`` gives each cell its strongest windows without a second pass over the rows."""

    def __init__(self, lin: Linearised, lib: _Library):
        t = np.concatenate([lin.rows.t[part.rows.ravel()] for part in lib.parts])  # the chunks' row order
        order = np.argsort(t, kind="stable")
        t = t[order]
        starts = window_starts(t)
        self.first, self.last = t[starts], t[np.r_[starts[1:], len(t)] - 1]
        step = np.zeros(len(t), np.int32)
        step[starts[1:]] = 1
        self.window = np.empty(len(t), np.int32)
        self.window[order] = np.cumsum(step, dtype=np.int32)
        self.gram = np.zeros((len(starts), len(lib.columns), len(lib.columns)))
        self.seen = 0

    def add(self, C: np.ndarray) -> None:
        w = self.window[self.seen:self.seen + len(C)]
        self.seen += len(C)
        runs = np.flatnonzero(np.r_[True, w[1:] != w[:-1], True])  # the chunk's rows by window
        for a, b in itertools.pairwise(runs):
            self.gram[w[a]] += C[a:b].T @ C[a:b]

    def placed(self, scored: list) -> list[StructureCell]:
        """The cells of ``scored`` ((cell, w) pairs) with their windows."""
        out = []
        for cell, w in scored:
            excess = np.einsum("i,gij,j->g", w, self.gram, w)
            out.append(dataclasses.replace(cell, windows=strongest(self.first, self.last, excess)))
        return out

"""Several recordings of one unit diagnosed as one: effects only the sessions together can show.

``pool(parts)`` joins the fitted per-sample models of the sessions (``evaluate``) into one
``Linearised`` that ``select``'s functions take unchanged:

- the rows of all sessions stacked; each session's times shifted past the one before (by
  whole ``BLOCK_S`` blocks and a gap), so the wild bootstrap's time blocks and the held-out
  stretches never join two sessions;
- the calibration (``S_a``, ``M_g``, ``k_a``, ``k_g``) one set of columns shared by every
  session: one unit; the biases (``PER_SESSION``: the turn-on bias of each power cycle) one
  block per session. A session whose temperature did not span enough to fit ``k`` has no
  ``k`` columns (its bias absorbs ``k (T - 25)``, as in its own diagnosis);
- the nuisances (gravity directions, bias walks, attitude paths) block-diagonal: the stage
  offsets concatenated, so the block-tridiagonal solver sees independent chains;
- each session's residual moved to one common calibration, ``r_s + J_s (x - x_s)`` at ``x``
  the sessions' mean: each session's own fit ``x_s`` differs a little (its estimation error;
  the Gauss-Newton step of the pooled system then moves all to the common optimum -- the
  difference the sessions disagree on is what a pooled term can explain).

``pooled_candidates`` stacks each session's catalogue columns (``select.candidates``) matched
by effect, sensor, regime and fixed parameters: one effect, one parameter set across the
sessions. ``diagnose_pooled`` then runs the single-session statistics (visible fraction, at
least any one session's own; score tests, Benjamini-Hochberg forward selection, wild bootstrap)
on the pooled system. The held-out check is by session from ``BY_SESSION_MIN`` sessions on
(``session_heldout``: each predicted by what the others fitted), else (and where a session's
absence leaves the terms undetermined) by each session's halves, each held out in turn
(``session_halves``: with two, one session alone could not determine an effect only both
together show; a shorter stretch its own session's bias walk bridges, taking up the term).
``pooled_walks`` estimates the bias walks from all sessions with one ``k``: the pooled model's
nuisances (``pipeline/pooled.py`` evaluates each session with them).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp

from ..errors import ImupipeError, SolverError
from ..models import TriadCalibration
from ..observations import Rests
from ..solvers.blocktri import Bordered
from ..solvers.brownian import estimate_intensity
from ..solvers.joint_ml import _dT
from .diagnose import catalogue_findings, coverage
from .evaluate import Evaluation
from .forward import Globals, Rows
from .linearised import Linearised
from .select import (BLOCK_S, BOOT_DRAWS, LONG_BLOCKS, Q_FDR, Candidate, Finding, HeldOut, _sensor_rms,
                     _stretch_of_rows, candidates, examine, heldout, rigid_walks)

PER_SESSION = ("b_a", "b_g")  # the turn-on bias of each power cycle: never shared
GAP_S = 60.0  # pooled time between two sessions (beyond any window's or block's reach)
SAME_UNIT_TOL = 0.02  # largest difference of S_a or M_g entries two recordings of one unit show
SAME_G_TOL = 1e-3  # relative difference of the sessions' local gravity
BY_SESSION_MIN = 3  # sessions from which a finding is held out by session (two: the other one alone
# could not determine an effect only the two together show)
PARTS_PER_SESSION = 2  # fewer sessions: each session's halves held out in turn


@dataclass
class PooledModel:
    """What ``select`` reads of ``lin.model``, for the pooled rows: the layout (``rows``,
    ``glob``, ``stages``), the rest count ``n`` and the motions' samples' motion ids (global),
    the whiteners (``W_sample`` one per motion sample) and gravity ``g``."""

    rows: Rows
    glob: Globals
    stages: SimpleNamespace
    n: int
    accel: SimpleNamespace
    W_a: np.ndarray
    W_g: np.ndarray
    W_sample: np.ndarray
    g: float
    shift: np.ndarray  # (S,) s: session s's time 0 in the pooled clock
    x_common: dict[str, np.ndarray]  # the shared blocks' linearisation point
    row_session: np.ndarray  # (N,) which session each row belongs to


def check_one_unit(parts: list[Linearised], names: list[str]) -> None:
    """Raise ``ImupipeError`` naming the session when the recordings are evidently not of one unit:
    a calibration far from the first's, or another local gravity."""
    first = parts[0]
    ref = first.model.unpack(first.x_g)
    for lin, name in zip(parts[1:], names[1:]):
        P = lin.model.unpack(lin.x_g)
        for key, what in (("S_a", "accelerometer scale/misalignment"), ("M_g", "gyro scale/misalignment")):
            d = float(np.abs(P[key] - ref[key]).max())
            if d > SAME_UNIT_TOL:
                raise ImupipeError(f"{name}: its {what} differs from {names[0]}'s by {d:.3g} (more than "
                                   f"{SAME_UNIT_TOL:g}, what one unit's recordings show): not the same unit; "
                                   "diagnose each session on its own")
        if abs(lin.model.g / first.model.g - 1) > SAME_G_TOL:
            raise ImupipeError(f"{name}: local gravity {lin.model.g:.5f} m/s^2, {names[0]} {first.model.g:.5f}: "
                               "pool only sessions recorded at one place")


def pool(parts: list[Linearised], x_common: dict[str, np.ndarray] | None = None) -> Linearised:
    """One ``Linearised`` of several sessions' fits (module docstring); ``lin.model`` is a
    ``PooledModel``. ``x_common``: the shared blocks' linearisation point (default the sessions'
    mean)."""
    shared: list[tuple[str, int]] = []
    for lin in parts:
        for name, s in lin.globals.slices.items():
            if name not in PER_SESSION and name not in dict(shared):
                shared.append((name, s.stop - s.start))
    blocks = shared + [(f"{name}#{i}", parts[i].globals.slices[name].stop - parts[i].globals.slices[name].start)
                       for i in range(len(parts)) for name in PER_SESSION if name in parts[i].globals.slices]
    glob = Globals.build(blocks)
    x_common = x_common or {name: np.mean([lin.x_g[lin.globals.slices[name]] for lin in parts
                                           if name in lin.globals.slices], axis=0) for name, _ in shared}
    x_g = np.zeros(glob.size)
    for name, _ in shared:
        x_g[glob.slices[name]] = x_common[name]
    r, J_g, shift = [], [], np.zeros(len(parts))
    for i, lin in enumerate(parts):
        J = np.zeros((len(lin.r), glob.size))
        ri = lin.r.copy()
        for name, s in lin.globals.slices.items():
            target = glob.slices[f"{name}#{i}" if name in PER_SESSION else name]
            J[:, target] = lin.J_g[:, s]
            if name in PER_SESSION:
                x_g[target] = lin.x_g[s]
            else:  # the residual at the common calibration (linearised)
                ri += lin.J_g[:, s] @ (x_common[name] - lin.x_g[s])
        r.append(ri)
        J_g.append(J)
        if i + 1 < len(parts):
            end = shift[i] + np.nanmax(lin.rows.t, initial=0.0) + GAP_S
            shift[i + 1] = np.ceil(end / BLOCK_S) * BLOCK_S
    offsets = [np.asarray(parts[0].model.stages.offsets)]
    for lin in parts[1:]:
        offsets.append(np.asarray(lin.model.stages.offsets)[1:] + offsets[-1][-1])
    offsets = np.concatenate(offsets)
    rows = Rows(np.concatenate([lin.rows.block for lin in parts]),
                np.concatenate([lin.rows.index for lin in parts]),
                np.concatenate([lin.rows.axis for lin in parts]),
                np.concatenate([np.where(np.isfinite(lin.rows.t), lin.rows.t, 0.0) + shift[i]
                                for i, lin in enumerate(parts)]))
    m = np.cumsum([0] + [lin.model.m for lin in parts])
    # motions numbered across the sessions: the rests' and motions' group ids (``raw_units``,
    # ``_row_groups``: rests 0..n-1, then n + motion) stay distinct
    motion = np.concatenate([lin.model.accel.motion + m[i] for i, lin in enumerate(parts)])
    model = PooledModel(
        rows=rows, glob=glob, stages=SimpleNamespace(offsets=offsets, size=int(offsets[-1])),
        n=sum(lin.model.n for lin in parts),
        accel=SimpleNamespace(motion=motion),
        W_a=np.concatenate([lin.model.W_a for lin in parts]), W_g=np.concatenate([lin.model.W_g for lin in parts]),
        W_sample=np.concatenate([np.broadcast_to(lin.model.W_sample, (len(lin.model.accel.t), 3, 3))
                                 for lin in parts]),
        g=float(np.mean([lin.model.g for lin in parts])), shift=shift, x_common=x_common,
        row_session=np.concatenate([np.full(len(lin.r), i) for i, lin in enumerate(parts)]))
    return Linearised(model, x_g, np.concatenate([lin.x_l for lin in parts]), np.concatenate(r),
                      np.vstack(J_g), sp.block_diag([lin.J_l for lin in parts], format="csr"),
                      max(lin.iterations for lin in parts), all(lin.converged for lin in parts))


def pooled_candidates(parts: list[Linearised], frames: list[np.ndarray], effects: dict
                      ) -> list[tuple[Candidate, list[Candidate | None]]]:
    """Each session's catalogue columns stacked, matched by effect, sensor, regime and fixed
    parameters (zero on a session that has no rows the term acts on), with each session's own
    candidate (None where it has none); the first session's frame names the parameters."""
    per = [{_key(c): c for c in candidates(lin, Q, effects)} for lin, Q in zip(parts, frames)]
    keys = list(dict.fromkeys(k for p in per for k in p))
    return [(_stacked(per, parts, key), [p.get(key) for p in per]) for key in keys]


def _stacked(per: list[dict], parts: list[Linearised], key: tuple, tau: float | None = None) -> Candidate:
    """The candidate ``key`` over the pooled rows: each session's columns (zeros where it has none),
    at the time constant ``tau`` when given (``select._profile`` profiles a pooled one too)."""
    own = [p.get(key) if tau is None or key not in p else p[key].profile(tau) for p in per]
    first = next(c for c in own if c is not None)
    cols = [c.columns if c is not None else np.zeros((len(lin.r), first.columns.shape[1]))
            for c, lin in zip(own, parts)]
    return Candidate(first.effect, first.sensor, first.regime, first.names, np.vstack(cols), first.to_params,
                     first.extra_dof, first.fixed, rejects=first.rejects, heldout_sensor=first.heldout_sensor,
                     profile=partial(_stacked, per, parts, key) if first.profile else None)


def _key(c: Candidate) -> tuple:
    return c.effect, c.sensor, c.regime, tuple(sorted(c.fixed.items()))


def diagnose_pooled(evaluations: list[Evaluation], effects: dict, sessions: list[str],
                    q: float = Q_FDR, files: list[str] | None = None, latitude_deg: float | None = None,
                    misfit: frozenset[str] = frozenset()) -> dict:
    """The pooled ``diagnosis.json`` of several sessions of one unit (``sessions``: their names).
    Findings are catalogue terms only (each session's own diagnosis maps its unexplained
    structure); a finding's ``windows`` are seconds from the first sample of the session that
    ``window_sessions`` names at the same place. ``files`` name the sessions in errors
    (default ``sessions``); ``latitude_deg`` the unit's, when known (``select._earth_rivals``);
    ``misfit`` the sensors whose noise floor a session's map finds misfit (``noise_misfit``)."""
    if len(evaluations) < 2:
        raise ImupipeError("a pooled diagnosis needs at least two sessions")
    parts = [ev.lin for ev in evaluations]
    check_one_unit(parts, files or sessions)
    lin = pool(parts)
    rigid, rigid_own = rigid_walks(lin), [rigid_walks(p) for p in parts]
    tested = []
    for c, own in pooled_candidates(parts, [ev.frame for ev in evaluations], effects):
        tested.append(examine(lin, c, rigid))
        # the pooled fraction is diluted by a session whose own parameters absorb the term whole (at
        # a constant temperature, a temperature term is a constant its bias takes); the pooled system
        # sees, along every direction, at least what any session alone sees of it
        tested[-1].visible = max([tested[-1].visible] + [examine(p, o, r).visible for p, o, r
                                                         in zip(parts, own, rigid_own) if o is not None])
    by_session = len(parts) >= BY_SESSION_MIN
    halves = session_halves(lin)
    _, findings, not_confirmed, _ = catalogue_findings(lin, tested, effects, q,
                                                       session_heldout(parts, halves) if by_session else halves,
                                                       latitude_deg, misfit)
    for f in findings:
        f["windows"], f["window_sessions"] = _session_windows(lin.model, f["windows"], sessions)
    return {"session": " + ".join(sessions), "sessions": sessions, "findings": findings,
            **coverage(tested, effects), "not_confirmed": not_confirmed,
            "fdr_q": q,
            "shared": [name for name in lin.globals.slices if "#" not in name],
            "per_session": list(PER_SESSION),
            "method": "the sessions' fitted per-sample models joined: rows stacked, the calibration shared, "
                      "the biases (turn-on) and every nuisance per session; score tests (the larger p of "
                      f"chi-square and a wild bootstrap over {BLOCK_S:g}-s time blocks within each session, "
                      f"{BOOT_DRAWS} draws; over {LONG_BLOCKS} spans of the pooled recordings for a sensor whose "
                      "noise floor a session's map finds misfit" + (f": {', '.join(sorted(misfit))}" if misfit else "")
                      + "), Benjamini-Hochberg forward selection with a backward check, "
                      + ("held out by session: each session predicted from the others' calibration and "
                         "terms, its own biases and nuisances refitted" if by_session else
                         "blocked cross-validation over each session's halves, each held out in turn")}


def _session_windows(model: PooledModel, wins: list, sessions: list[str]) -> tuple[list, list]:
    """Pooled-clock windows as (seconds from their session's first row, the session's name)."""
    out, names = [], []
    for a, b in wins:
        i = int(np.searchsorted(model.shift, a, "right") - 1)
        out.append([a - model.shift[i], b - model.shift[i]])
        names.append(sessions[i])
    return out, names


def session_halves(lin: Linearised):
    """The blocked held-out check (``select.heldout``) over each session's halves of the pooled ``lin``."""
    return partial(heldout, stretch=_stretch_of_rows(lin, PARTS_PER_SESSION, lin.model.row_session))


def session_heldout(parts: list[Linearised], fallback):
    """The held-out check by session (``select.heldout``'s face): each session in turn predicted
    by the calibration and the terms fitted to the others (one linearised step), its own biases
    and nuisances refitted to it, without and with the finding's term; the RMS and the paired
    z over every session's rests and motions (``_sensor_rms``). A session without which the
    training sessions cannot determine the terms falls back to ``fallback`` (``session_halves``)."""

    def held_out(lin: Linearised, rp: np.ndarray, finding: Finding, others: list[Finding]
                 ) -> HeldOut:
        X = np.hstack([f.tested.candidate.columns for f in others] + [finding.tested.candidate.columns])
        k_base = X.shape[1] - finding.tested.candidate.columns.shape[1]
        before, after = np.zeros_like(rp), np.zeros_like(rp)
        session = lin.model.row_session
        try:
            for k in range(len(parts)):
                rows = session == k
                before[rows], after[rows] = _predict_session(parts, k, lin.model.x_common, X[~rows], X[rows],
                                                             k_base)
        except (np.linalg.LinAlgError, SolverError):
            return fallback(lin, rp, finding, others)
        return _sensor_rms(lin, finding, before, after)

    return held_out


def _predict_session(parts: list[Linearised], k: int, x_common: dict, X_train: np.ndarray, X_k: np.ndarray,
                     k_base: int) -> tuple[np.ndarray, np.ndarray]:
    """Session ``k``'s residual under the shared calibration and the term columns fitted to the
    other sessions (``X_train``, their rows), its own biases and nuisances (and any shared block
    the others do not determine) fitted to it: with the term columns up to ``k_base`` and with all."""
    train = pool([p for i, p in enumerate(parts) if i != k], x_common)
    part = parts[k]
    out = []
    for n_cols in (k_base, X_train.shape[1]):
        J = np.hstack([train.J_g, X_train[:, :n_cols]])
        step, _ = Bordered(J, train.J_l, train.model.stages.offsets).step(train.r)
        e, own = part.r.copy(), []
        for name, s in part.globals.slices.items():
            if name in PER_SESSION or name not in train.globals.slices:
                own.append(part.J_g[:, s])
            else:
                e += part.J_g[:, s] @ (x_common[name] + step[train.globals.slices[name]] - part.x_g[s])
        e += X_k[:, :n_cols] @ step[train.J_g.shape[1]:]
        F = np.hstack(own)
        d_own, d_l = Bordered(F, part.J_l, part.model.stages.offsets).step(e)
        out.append(e + F @ d_own + part.J_l @ d_l)
    return out[0], out[1]


def pooled_walks(rests: list[Rests], accel: list[TriadCalibration], gyro: list[TriadCalibration],
                 gravity: float) -> tuple[float, float]:
    """The accelerometer's and the gyro's bias random-walk intensities (REML, ``brownian``) from
    every session's rests with one temperature coefficient ``k`` (each session's levels, gravity
    directions and accelerometer calibration profiled on their own). A walk that one session's own
    ``k`` takes up (in a warm-up the temperature rises monotonically, like a drift, so a single
    session's estimate may miss the walk) shows here as the sessions' ``k`` disagreeing: left out
    of the pooled model, it would pass for a temperature curvature. Estimated at the likelihood's
    maximum, not detected at 5 % as the calibration's are: a weak walk set to zero (measured: a
    unit's walk of 1e-12 rad^2/s^3 estimated zero in both its warm-ups) left its wander to pass
    for a curvature in a pooled null."""
    t_start, t_end, offset = [], [], 0.0
    for R in rests:  # one clock; the per-session levels cut the walk between sessions
        t_start.append(R.t_start_s + offset - R.t_start_s[0])
        t_end.append(R.t_end_s + offset - R.t_start_s[0])
        offset = t_end[-1][-1] + GAP_S
    t_start, t_end = np.concatenate(t_start), np.concatenate(t_end)
    own, shared, r, var, H = [], [], [], [], []
    for R, g in zip(rests, gyro):
        dT = _dT(R)
        a = R.need("accel")
        r.append(R.need("gyro") - g.b0 - np.outer(dT, gyro[0].k))
        own.append(np.column_stack([np.ones(len(R)), a / np.linalg.norm(a, axis=1, keepdims=True)]))
        shared.append(dT[:, None])
        var.append(np.diagonal(R.cov_of_mean("gyro"), axis1=1, axis2=2))
    X = np.hstack([sp.block_diag(own).toarray(), np.vstack(shared)])
    q_g, _ = estimate_intensity(t_start, t_end, np.vstack(r), np.vstack(var), X, min_lr=0.0)
    own, shared, r, var = [], [], [], []
    for R, cal in zip(rests, accel):
        dT = _dT(R)
        y = R.need("accel")

        def norm_error(theta: np.ndarray) -> np.ndarray:
            M, b, k = theta[:9].reshape(3, 3), theta[9:12], theta[12:]
            return np.linalg.norm((y - b - np.outer(dT, k)) @ M.T, axis=1) - gravity

        theta = np.concatenate([cal.M.ravel(), cal.b0, accel[0].k])
        r.append(norm_error(theta))
        D = np.empty((len(y), len(theta)))
        for c in range(len(theta)):  # what the accelerometer's own fit (M, b) and the shared k absorb
            h = 1e-7 * max(1.0, abs(theta[c]))
            step = h * np.eye(len(theta))[c]
            D[:, c] = (norm_error(theta + step) - norm_error(theta - step)) / (2 * h)
        own.append(D[:, :12])
        shared.append(D[:, 12:])
        x = (y - cal.b0 - np.outer(dT, accel[0].k)) @ cal.M.T
        H.append((x / np.linalg.norm(x, axis=1, keepdims=True)) @ cal.M)  # the walk seen along gravity
        var.append(np.einsum("ni,nij,nj->n", H[-1], R.cov_of_mean("accel"), H[-1]))
    X = np.hstack([sp.block_diag(own).toarray(), np.vstack(shared)])
    q_a, _ = estimate_intensity(t_start, t_end, np.concatenate(r)[:, None], np.concatenate(var)[:, None], X,
                                np.vstack(H), min_lr=0.0)
    return q_a, q_g

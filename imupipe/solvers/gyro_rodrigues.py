"""Method A gyroscope: Rodrigues' formula over turns between rests (eqs. 27-37).

Each turn moves the corrected gravity from ``g0`` to ``g1``; the half finite
rotation ``Y`` measured by the corrected gyro must satisfy ``G Y = 0`` with
``G = C C^T + S S^T - I`` (eq. 31). With ``Y ~ M Y~`` and ``M00 = 1`` this is
linear in the other 8 entries of M (eqs. 33-36); the scale comes from the turn
angles (eq. 37). A turn's bias is the mean of the rests before and after it; the
returned ``b0`` is their mean over the turns the fit used.

``exact_rotation = True`` replaces the small-angle sum of eq. (29) by the rate
integrated as a rotation: ``Y~`` becomes ``M^-1 phi(M)``, with ``phi`` the
rotation vector of the corrected rates, iterated to a fixed point, and the scale
fits gravity after each turn to gravity before carried through it by the gyro
(Rodrigues' relation for finite rotations); turns of tens of degrees, or not about
a fixed axis, then add no bias.
"""

from __future__ import annotations

import warnings
from typing import ClassVar

import numpy as np
from pydantic import Field

from ..components import Params
from ..errors import SolverError
from ..observations import GyroObservations, TriadFit
from ..rotations import (
    carry,
    hold_intervals,
    pad_turns,
    quat_to_rotvec,
    turn_quaternions,
    turn_rotations,
)

MIN_TURNS = 10  # 8 unknowns, one informative equation per turn


class GyroRodriguesParams(Params):
    """``exact_rotation``: integrate the rate as a rotation (True) or the paper's
    small-angle sum (False). ``min_tilt_deg``: turns that move gravity by less are
    uninformative (rotation about the vertical) and skipped. ``iterations``: fixed-point
    passes of the exact mode (at most), stopping when M changes by less than
    ``tolerance``. ``max_scale_turn_deg``: in small-angle mode the scale (eq. 37
    over all turns) uses turns up to this angle only (eq. 28 fails for large turns)."""

    exact_rotation: bool = True
    min_tilt_deg: float = Field(0.5, ge=0, lt=180)
    min_turns: int = Field(MIN_TURNS, ge=8)
    iterations: int = Field(40, ge=1)
    tolerance: float = Field(1e-10, gt=0)
    max_scale_turn_deg: float = Field(60.0, gt=0)


Rates = tuple[np.ndarray, np.ndarray]  # padded turns: rates (m, k, 3) rad/s, hold intervals (m, k) s


def turn_bias(obs: GyroObservations) -> np.ndarray:
    """(m, 3) rad/s: each turn's bias, the mean of the rests before and after it."""
    return 0.5 * (obs.bias[obs.turns.before] + obs.bias[obs.turns.after])


def turn_rates(obs: GyroObservations) -> Rates:
    """Padded turns: raw rates minus each turn's bias, and each sample's hold interval."""
    rate, dt = pad_turns(obs.turns.t, obs.turns.gyro, hold_intervals)
    return rate - turn_bias(obs)[:, None, :], dt


def rate_unit(rates: Rates, tilt_rad: np.ndarray) -> float:
    """Rough rad/s per raw unit (1 for rad/s data): a turn tilts gravity by at most the angle
    it turns through, so ``tilt / |sum w dt|`` is near the unit for turns about a horizontal
    axis and below it otherwise; the upper decile. Solving in these units lets ``M00 = 1``
    and the exact rotations start near the truth for raw counts too."""
    rate, dt = rates
    angle = np.linalg.norm(np.einsum("mk,mki->mi", dt, rate), axis=1)
    ok = (angle > 0) & (tilt_rad > np.radians(1.0))
    return float(np.quantile(tilt_rad[ok] / angle[ok], 0.9)) if ok.any() else 1.0


def take(rates: Rates, index) -> Rates:
    """The turns at ``index`` of padded ``rates``."""
    return rates[0][index], rates[1][index]


def rotations_of(rates: Rates, M: np.ndarray, exact: bool, turns=None) -> np.ndarray:
    """Rotation vectors (m, 3) rad of the corrected rates ``w @ M.T`` of each motion (``turns``:
    those alone): integrated as rotations (exact) or summed as in eq. (29)."""
    rate, dt = rates
    if exact:
        return quat_to_rotvec(turn_quaternions(rate, dt, M, turns))
    if turns is not None:
        rate, dt = take(rates, turns)
    return np.einsum("mk,mki->mi", dt, rate @ M.T)


def carried_gravity(rates: Rates, M: np.ndarray, g0: np.ndarray, turns=None) -> np.ndarray:
    """(m, 3) gravity before each turn (of ``turns``) carried through it by the corrected rates."""
    return carry(turn_rotations(*rates, M, turns), g0)


def bias_of_turns(obs: GyroObservations, turns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bias the fit used (3,) rad/s: the mean over ``turns`` of each turn's bias (the
    rests before and after it), and its (3, 3) covariance from the scatter of the rests."""
    weight = np.zeros(len(obs.bias))
    np.add.at(weight, obs.turns.before[turns], 0.5 / len(turns))
    np.add.at(weight, obs.turns.after[turns], 0.5 / len(turns))
    cov = (weight @ weight) * np.cov(obs.bias.T) if len(obs.bias) > 1 else np.full((3, 3), np.nan)
    return weight @ obs.bias, cov


def rodrigues_error(g0: np.ndarray, g1: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Eq. (38): ``E = (g1 - g0) + Y x (g1 + g0)``, (3,) or (m, 3)."""
    return (g1 - g0) + np.cross(Y, g1 + g0)


def angle_error(g0: np.ndarray, g1: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Eq. (39): turn-angle error (rad) for each turn, rows of (m, 3) arrays."""
    E = rodrigues_error(g0, g1, Y)
    e = Y / np.maximum(np.linalg.norm(Y, axis=-1, keepdims=True), 1e-300)
    c = np.cross(e, g1 + g0)
    return 2 * np.sum(E * c, axis=-1) / np.maximum(np.sum(c * c, axis=-1), 1e-300)


def design(G: np.ndarray, Yt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows (3, 8) and right side (3,) of eq. (35) for one turn (misprint of eq. 34 fixed)."""
    y0, y1, y2 = Yt
    H = np.column_stack([G[:, 0] * y1, G[:, 0] * y2, G[:, 1] * y0, G[:, 1] * y1, G[:, 1] * y2,
                         G[:, 2] * y0, G[:, 2] * y1, G[:, 2] * y2])
    return H, -y0 * G[:, 0]


class GyroRodrigues:
    """Gyroscope solver of method A: ``solve(GyroObservations) -> TriadFit``."""

    name = "gyro_rodrigues"
    kind = "gyro"
    version = "3"  # 2: b0 from the rests around the turns used; 3: any rate unit (counts)
    params: ClassVar[type[Params]] = GyroRodriguesParams

    def solve(self, obs: GyroObservations, params: GyroRodriguesParams) -> TriadFit:
        g = obs.gravity / np.linalg.norm(obs.gravity, axis=1, keepdims=True)
        g0, g1 = g[obs.turns.before], g[obs.turns.after]
        tilt = np.degrees(np.arccos(np.clip(np.sum(g0 * g1, axis=1), -1, 1)))
        use = np.flatnonzero(tilt >= params.min_tilt_deg)
        if len(use) < params.min_turns:
            raise SolverError(
                f"gyro: {len(use)} of {len(obs.turns)} turns tilt gravity by >= "
                f"{params.min_tilt_deg} deg; eqs. (31)-(36) need at least {params.min_turns} turns "
                "about varied horizontal axes: record more rest-turn-rest motions"
            )
        rates = turn_rates(obs)
        unit = rate_unit(take(rates, use), np.radians(tilt[use]))
        rates[0][...] *= unit  # solved in ~rad/s; M returned per raw unit
        C = np.cross(g0, g1)
        C /= np.linalg.norm(C, axis=1, keepdims=True).clip(1e-300)
        S = (g0 + g1) / np.linalg.norm(g0 + g1, axis=1, keepdims=True).clip(1e-300)
        Gs = np.einsum("ki,kj->kij", C, C) + np.einsum("ki,kj->kij", S, S) - np.eye(3)  # Eq. (31)

        Gu = Gs[use]

        def step(M: np.ndarray, beta: float | None):
            """One pass: LS of eq. (36) with Y~ from the current M, then the scale (eq. 37)."""
            # Y~ such that M Y~ is the rotation of the corrected rates (eq. 29 when small-angle)
            Yts = rotations_of(rates, M, True, use) @ np.linalg.inv(M).T if params.exact_rotation \
                else rotations_of(rates, np.eye(3), False, use)
            rows = [design(G, Yt / max(np.linalg.norm(Yt), 1e-12)) for G, Yt in zip(Gu, Yts, strict=True)]
            H, Z = np.vstack([r[0] for r in rows]), np.concatenate([r[1] for r in rows])
            m, *_ = np.linalg.lstsq(H, Z, rcond=None)  # Eq. (36)
            M_hat = np.array([[1.0, m[0], m[1]], [m[2], m[3], m[4]], [m[5], m[6], m[7]]])
            beta, sel = self._scale(obs, rates, M_hat, g0, g1, use, params, beta)
            return beta * M_hat, (H, Z, m, M_hat, beta, sel)  # Eq. (37)

        # fixed point M = F(M) (exact mode), with Anderson acceleration: large turns converge slowly
        M, state = step(np.eye(3), None)
        xs, fs = [], []
        passes, converged = 0, not params.exact_rotation
        for passes in range(1, params.iterations if params.exact_rotation else 1):
            M_next, state_next = step(M, state[4])
            f = (M_next - M).ravel()
            xs.append(M.ravel())
            fs.append(f)
            xs, fs = xs[-4:], fs[-4:]
            if np.abs(f).max() < params.tolerance:
                M, state, converged = M_next, state_next, True
                break
            if len(fs) > 1:
                dF = np.column_stack([fs[i + 1] - fs[i] for i in range(len(fs) - 1)])
                dX = np.column_stack([xs[i + 1] - xs[i] for i in range(len(xs) - 1)])
                gamma, *_ = np.linalg.lstsq(dF, f, rcond=None)
                M = (M.ravel() + f - (dX + dF) @ gamma).reshape(3, 3)
            else:
                M = M_next
            state = state_next
        H, Z, m, M_hat, beta, sel = state
        M = beta * M_hat
        if not converged:
            warnings.warn(f"gyro: the exact-rotation fixed point did not settle in {params.iterations} "
                          f"passes (last change {np.abs(f).max():.1e}); raise `iterations`", stacklevel=2)

        cov = np.zeros((12, 12))
        cov[:9, :9] = self._covariance(H, Z, m, beta, rates, sel, g0, g1,
                                        params.exact_rotation or obs.roll_turn is not None,
                                        self._scale_noise(obs, rates, sel, unit))
        b0, cov[9:, 9:] = bias_of_turns(obs, np.union1d(use, sel))
        details = {
            "n_turns_used": len(use), "n_turns": len(obs.turns),
            "exact_rotation": params.exact_rotation, "beta": float(beta), "passes": passes + 1,
            "converged": converged,
            "scale_from": "roll turn (eq. 37)" if obs.roll_turn is not None else "all turns",
            "max_turn_deg": float(np.degrees(np.linalg.norm(
                rotations_of(rates, M, True, use), axis=1)).max()),
        }
        cov[:9, :9] *= unit**2
        details["rate_unit"] = unit
        return TriadFit(unit * M, b0, cov, details)

    @staticmethod
    def _scale(obs, rates, M_hat, g0, g1, use, params, beta_prev) -> tuple[float, list[int]]:
        """Scale beta of eq. (37) and the turns it used: the roll turn alone, else all turns.

        Exact mode: Gauss-Newton steps on the gravity carried through each turn by the
        scaled rates (from ``beta_prev`` when given); small-angle mode: LS of eq. (38).
        """
        exact = params.exact_rotation
        sel = [obs.roll_turn] if obs.roll_turn is not None else list(use)
        if obs.roll_turn is not None or not exact or beta_prev is None:
            phis = rotations_of(rates, M_hat, True, sel)
        if obs.roll_turn is None and not exact:
            small = np.degrees(np.linalg.norm(phis, axis=1)) <= params.max_scale_turn_deg
            if small.sum() < 1:
                raise SolverError(f"gyro: no turn below {params.max_scale_turn_deg} deg to fix the "
                                  "scale; give the roll turn (eq. 37) or record small turns")
            sel = [j for j, keep in zip(sel, small, strict=True) if keep]
            phis = phis[small]
        if obs.roll_turn is not None and (beta_prev is None or not exact):
            d_gamma = np.arccos(np.clip(g0[sel[0]] @ g1[sel[0]], -1, 1))
            beta = float(d_gamma / np.linalg.norm(phis[0]))  # Eq. (37)
            if not exact:
                return beta, sel
            # exact: refine on the carried gravity below, so a roll axis a few degrees off
            # the horizontal (angle between the g's != turn angle) biases nothing
        elif beta_prev is None or not exact:
            s, d = g0[sel] + g1[sel], g1[sel] - g0[sel]
            c = np.cross(0.5 * phis, s)
            beta = float(-np.sum(c * d) / np.sum(c * c))  # small-angle LS of eq. (38)
            if not exact:
                return beta, sel
        else:
            beta = beta_prev

        def resid(b: float) -> np.ndarray:
            # gravity before, carried by the scaled rates as a finite rotation, vs gravity after:
            # Rodrigues' relation without tan(chi/2), well-conditioned at any turn angle
            return (carried_gravity(rates, b * M_hat, g0[sel], sel) - g1[sel]).ravel()

        for _ in range(2 if beta_prev is not None else 4):
            r0 = resid(beta)
            h = 1e-6 * beta
            J = (resid(beta + h) - r0) / h
            beta -= float(J @ r0 / (J @ J))
        return beta, sel

    @staticmethod
    def _scale_noise(obs: GyroObservations, rates, sel, unit: float = 1.0) -> float:
        """Variance per component of the scale residuals the noise model predicts (0: none):
        gravity noise at both rests, white gyro noise and bias error integrated over each turn;
        ``unit`` converts the raw rate noise to the solving units (``rate_unit``)."""
        if obs.gravity_cov is None or obs.rate_sigma is None:
            return 0.0
        b, a = obs.turns.before[sel], obs.turns.after[sel]
        dt = rates[1][sel]
        span = dt.sum(axis=1)

        def trace(cov: np.ndarray) -> np.ndarray:
            return np.trace(cov, axis1=1, axis2=2)

        grav = (trace(obs.gravity_cov[b]) + trace(obs.gravity_cov[a])) / 3
        white = float(np.mean(obs.rate_sigma**2)) * np.sum(dt * dt, axis=1) * unit**2
        bias = (trace(obs.bias_cov[b]) + trace(obs.bias_cov[a])) / 12 * span**2 * unit**2
        return float(np.mean(grav + white + bias))

    @staticmethod
    def _covariance(H, Z, m, beta, rates, sel, g0, g1, exact_scale: bool,
                    noise_var: float = 0.0) -> np.ndarray:
        """(9, 9) covariance of vec(M) from the stacked residuals, linearised at the solution.

        The 8 entries m come from the rows of eq. (35) alone; beta minimises the scale
        residuals (the gravity carried through the scale turns, exact; eq. 38 small-angle)
        given m, so it inherits m's uncertainty through d beta / d m plus its own.
        """
        a, b = g0[sel], g1[sel]

        def scale_resid(x: np.ndarray) -> np.ndarray:
            Mx = x[8] * np.array([[1.0, x[0], x[1]], [x[2], x[3], x[4]], [x[5], x[6], x[7]]])
            if exact_scale:
                return (carried_gravity(rates, Mx, a, sel) - b).ravel()
            phis = rotations_of(rates, Mx, False, sel)
            return ((b - a) + np.cross(0.5 * phis, a + b)).ravel()  # Eq. (38)

        x0 = np.append(m, beta)
        r_s = scale_resid(x0)
        J_s = np.empty((len(r_s), 9))
        for i in range(9):
            h = 1e-6 * max(abs(x0[i]), 1e-2)
            xp = x0.copy()
            xp[i] += h
            J_s[:, i] = (scale_resid(xp) - r_s) / h
        r_h = Z - H @ m
        s2_h = float(r_h @ r_h) / max(len(Z) // 3 - 8, 1)  # G has rank 1: one equation per turn
        dof_s = max((2 if exact_scale else 3) * len(sel) - 1, 1)
        s2_s = max(float(r_s @ r_s) / dof_s, noise_var, 1e-30)  # one turn: trust the noise model
        # the estimator: m from eq. (35) alone; beta minimises the scale residuals given m
        cov_m = s2_h * np.linalg.pinv(H.T @ H)
        J_m, J_b = J_s[:, :8], J_s[:, 8]
        dbeta_dm = -(J_b @ J_m) / (J_b @ J_b)
        A = np.vstack([np.eye(8), dbeta_dm])
        cov_x = A @ cov_m @ A.T
        cov_x[8, 8] += s2_s / (J_b @ J_b)
        J = np.zeros((9, 9))  # d vec(M) / d (m, beta)
        for col, idx in enumerate(range(1, 9)):
            J[idx, col] = beta
        J[:, 8] = np.concatenate([[1.0], m])  # vec(M_hat)
        return J @ cov_x @ J.T


COMPONENTS = [GyroRodrigues()]

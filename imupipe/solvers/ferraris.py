"""Ferraris et al. (1995) six-pose + known-angle-turn calibration, equation by equation as imucal
implements it (mad-lab-fau/imucal, ``FerrarisCalibration.compute``).

Accelerometer from the six pose means ``U_p`` (columns: the mean with +x, +y, +z up) and
``U_n`` (-x, -y, -z up): bias ``b = diag(U_p + U_n) / 2`` (eq. 20), ``U_d = U_p - U_n``
(eq. 21), scale ``K = diag(|rows of U_d|) / 2g`` (eq. 23), ``R = K^-1 U_d / 2g`` (eq. 22);
the correction ``x = R^-1 K^-1 (y - b)``. Gyroscope bias: the mean of every pose sample;
optionally the g-sensitivity ``K_ga = (U_gp - U_ga) / 2g`` (eq. 9, imucal's default);
the bias-removed rate integrated over each turn (eqs. 13-14) gives ``W``, and
``W / angle = K_g R_g`` (eqs. 12, 15) with ``K_g`` the row norms.

Uncertainties propagate the white noise of the pose means and of the turn integrals
through these equations (forward differences); the model has no spare turn, so the
gyroscope fit has no residual of its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.linalg import inv

from ..components import Params
from ..errors import SolverError
from ..observations import TriadFit
from .ellipsoid_cholesky import jacobian

POSES = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
TURNS = ("x_rot", "y_rot", "z_rot")


@dataclass(frozen=True)
class FerrarisObservations:
    """Samples of each section (raw, SI: m/s^2, rad/s), keyed by imucal's names.

    ``pose_acc[p]``, ``pose_gyr[p]``: (n, 3) samples of pose ``p``; ``turn_acc[t]``,
    ``turn_gyr[t]``: (n, 3) samples of turn ``t``; ``turn_dt[t]``: (n,) seconds each
    sample stands for; ``g``: local gravity, m/s^2; ``angle_rad``: the turns' known
    angle (signed; None: a full turn in the direction the gyro saw).
    """

    pose_acc: dict
    pose_gyr: dict
    turn_acc: dict
    turn_gyr: dict
    turn_dt: dict
    g: float
    angle_rad: float | None = None


class FerrarisParams(Params):
    """``g_sensitivity``: also fit imucal's gyro g-sensitivity K_ga from the pose pairs and
    remove it from the turns (it is reported in details; calibration.json's correction has no
    such term, so off by default)."""

    g_sensitivity: bool = False


def accel_fit(U_p: np.ndarray, U_n: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """(M, b, details) from the pose-mean matrices (columns x, y, z)."""
    b = np.diag(U_p + U_n) / 2  # Eq. (20)
    U_d = U_p - U_n  # Eq. (21)
    K = np.diag(np.sqrt(np.diag(U_d @ U_d.T)) / (2 * g))  # Eq. (23)
    R = inv(K) @ U_d / (2 * g)  # Eq. (22)
    return inv(R) @ inv(K), b, {"K": np.diag(K).tolist(), "R": R.tolist()}


def gyro_fit(W: np.ndarray, angle: float) -> tuple[np.ndarray, dict]:
    """(M, details) from the integrated turns ``W`` (columns x, y, z) and the known angle."""
    mult = W / angle  # Eq. (15)
    K = np.diag(np.sqrt(np.diag(mult @ mult.T)))  # Eq. (12)
    R = inv(K) @ mult
    return inv(R) @ inv(K), {"K": np.diag(K).tolist(), "R": R.tolist()}


class Ferraris:
    """``solve(FerrarisObservations) -> {"accel": TriadFit, "gyro": TriadFit}``."""

    name = "ferraris"
    kind = "ferraris"
    version = "1"
    params: ClassVar[type[Params]] = FerrarisParams

    def solve(self, obs: FerrarisObservations, params: FerrarisParams) -> dict[str, TriadFit]:
        g = obs.g
        mean = {p: obs.pose_acc[p].mean(axis=0) for p in POSES}
        cov_mean = {p: _cov(obs.pose_acc[p]) / len(obs.pose_acc[p]) for p in POSES}
        U_p = np.column_stack([mean[f"{a}_p"] for a in "xyz"])
        U_n = np.column_stack([mean[f"{a}_a"] for a in "xyz"])
        M_a, b_a, det_a = accel_fit(U_p, U_n, g)

        def pack_a(v: np.ndarray) -> np.ndarray:
            m = v.reshape(6, 3)
            M, b, _ = accel_fit(m[0::2].T, m[1::2].T, g)
            return np.concatenate([M.ravel(), b])

        v0 = np.concatenate([mean[p] for p in POSES])
        J = jacobian(pack_a, v0)
        C = _block([cov_mean[p] for p in POSES])
        fit_a = TriadFit(M_a, b_a, J @ C @ J.T, {
            "method": "Ferraris six poses (imucal eqs. 19-23)", "K": det_a["K"], "R": det_a["R"],
            "g_m_s2": g, "poses": {p: len(obs.pose_acc[p]) for p in POSES}})

        # gyroscope: bias from every pose sample, then the turns
        all_g = np.vstack([obs.pose_gyr[p] for p in POSES])
        b_g = all_g.mean(axis=0)
        sigma2 = np.median([np.diag(_cov(obs.pose_gyr[p])) for p in POSES], axis=0)
        K_ga = np.zeros((3, 3))
        if params.g_sensitivity:
            U_gp = np.column_stack([obs.pose_gyr[f"{a}_p"].mean(axis=0) for a in "xyz"])
            U_ga = np.column_stack([obs.pose_gyr[f"{a}_a"].mean(axis=0) for a in "xyz"])
            K_ga = (U_gp - U_ga) / (2 * g)  # Eq. (9)
        raw, n_dt, acc_int = {}, {}, {}
        for a, t in zip("xyz", TURNS, strict=True):
            dt = obs.turn_dt[t]
            raw[a] = (obs.turn_gyr[t] * dt[:, None]).sum(axis=0)  # Eqs. (13)-(14)
            n_dt[a] = dt.sum()
            acc_int[a] = ((obs.turn_acc[t] - b_a) @ M_a.T * dt[:, None]).sum(axis=0)
        W = np.column_stack([raw[a] - n_dt[a] * b_g - K_ga @ acc_int[a] for a in "xyz"])
        seen = np.degrees(np.diag(W))
        if obs.angle_rad is None:
            angle = np.sign(seen) * 2 * np.pi
            if not (np.all(angle > 0) or np.all(angle < 0)):
                raise SolverError(
                    f"ferraris: the turns went different ways (x, y, z integrate to "
                    f"{np.round(seen, 1).tolist()} deg); turn all three the same way, or give "
                    "turn_angle_deg for each recording made that way")
            angle = float(angle[0])
        else:
            angle = obs.angle_rad
        ratio = np.diag(W) / angle
        if np.any(ratio <= 0) or np.any(np.abs(ratio - 1) > 0.25):
            raise SolverError(
                f"ferraris: the turns integrate to {np.round(seen, 1).tolist()} deg about x, y, z "
                f"but the known angle is {np.degrees(angle):.0f} deg: "
                + ("a turn went the other way; set turn_angle_deg to the opposite sign (or leave it "
                   "unset: a full turn in the direction seen)" if np.any(ratio <= 0) else
                   "the turn sections do not hold one turn each, or the gyro unit is wrong; check "
                   "the section list and the manifest's gyro unit"))
        M_g, det_g = gyro_fit(W, angle)

        def pack_g(v: np.ndarray) -> np.ndarray:
            bg, cols = v[:3], v[3:].reshape(3, 3)
            Wv = np.column_stack([cols[i] - n_dt[a] * bg - K_ga @ acc_int[a]
                                  for i, a in enumerate("xyz")])
            M, _ = gyro_fit(Wv, angle)
            return np.concatenate([M.ravel(), bg])

        w0 = np.concatenate([b_g, raw["x"], raw["y"], raw["z"]])
        J = jacobian(pack_g, w0)
        C = _block([np.diag(sigma2) / len(all_g)]
                   + [np.diag(sigma2) * float((obs.turn_dt[t] ** 2).sum()) for t in TURNS])
        fit_g = TriadFit(M_g, b_g, J @ C @ J.T, {
            "method": "Ferraris known-angle turns (imucal eqs. 9-15)", "K": det_g["K"],
            "R": det_g["R"], "turn_angle_deg": float(np.degrees(angle)),
            "turn_angle_source": "given" if obs.angle_rad is not None else "full turn, sign seen",
            "turns_integrated_deg": seen.tolist(),
            "g_sensitivity": K_ga.tolist() if params.g_sensitivity else None,
            "g_sensitivity_note": ("rad/s per m/s^2, removed from the turns; calibration.json's "
                                   "correction does not apply it") if params.g_sensitivity else None,
            "turns": {t: len(obs.turn_gyr[t]) for t in TURNS}})
        return {"accel": fit_a, "gyro": fit_g}


def _cov(x: np.ndarray) -> np.ndarray:
    return np.cov(x.T) if len(x) > 1 else np.zeros((3, 3))


def _block(blocks: list[np.ndarray]) -> np.ndarray:
    n = sum(len(b) for b in blocks)
    out, i = np.zeros((n, n)), 0
    for b in blocks:
        out[i:i + len(b), i:i + len(b)] = b
        i += len(b)
    return out


COMPONENTS = [Ferraris()]

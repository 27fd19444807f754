"""Reproduce Tables 1-3 of the sphere-rig paper (Vyalkov & Vyalkova 2023) by Monte Carlo.

Run: ``/work/venv/bin/python bench/sphere_rig_tables.py [--sets 100] [--seed 0]``

The paper's setup (seeds/vyalkov2023-sphere-rig.txt, "Modelling accelerometer
calibration"): model (1) ``y = M_a x + b + w`` with the printed M_a (forward: the
N = 0 columns of Tables 2-3 are M_a e + b), b in g, w ~ N(0, 0.5 mg); 100 sets of N
random positions "uniform over the full solid angle"; estimator: ellipsoid LS with
D33 = 0 (eqs. 7-12), b = -D0^-1 D1 (13), Cholesky D0 = L L^T (15), scale and rotation
from the reference positions Y up (17-18) and X up (19), correction (20). Tables:
mean and 95 % interval (mg) of the bias error (T1) and of the corrected gravity
vector's error with gravity along OX (T2) and OZ (T3).

Beside every cell: the paper's value and the Cramer-Rao bound (95 % half-width =
1.96 sqrt(CRB)) of the 12-parameter model (M_a 9, b 3) with the orientations of the
N positions as nuisance parameters, at the true parameters, with sigma, under the
constraints the paper's references impose (corrected Y-up reading = e_y exactly,
corrected X-up reading has zero z). Fisher information is computed numerically as
N times its mean over 20000 directions of the position distribution.
"""

from __future__ import annotations

import argparse

import numpy as np

M_A = np.array([[0.947, 0.059, -0.045], [-0.068, 1.046, 0.058], [0.06, -0.047, 1.017]])
B = np.array([0.01, -0.05, 0.02])
SIGMA = 0.5e-3  # g
NS = (10, 50, 200, 500, 1000)
E = np.eye(3)

PAPER = {  # (mean, half-width) mg; None where the paper prints only "+-x"
    "T1": {"b_x": [(-0.6, 17), (-0.1, 0.15), (0.05, 0.08), (0.04, 0.04), (0.01, 0.03)],
           "b_y": [(0.8, 17), (-0.1, 0.28), (0.05, 0.14), (0.04, 0.09), (0.01, 0.06)],
           "b_z": [(1.0, 15), (-0.1, 0.28), (0.06, 0.13), (0.04, 0.07), (0.01, 0.05)]},
    "T2": {"a_x": [(2.1, 36), (None, 0.66), (None, 0.27), (None, 0.20), (None, 0.13)],
           "a_y": [(0.8, 24), (0.1, 0.73), (None, 0.34), (None, 0.20), (None, 0.15)],
           "a_z": [(0.1, 0.01), (-0.001, None), (-0.001, None), (-0.001, None), (-0.001, None)]},
    "T3": {"a_x": [(0.2, 27), (0.1, 0.78), (-0.1, 0.38), (-0.1, 0.22), (None, 0.14)],
           "a_y": [(-1.0, 41), (0.1, 0.81), (-0.1, 0.34), (-0.1, 0.23), (None, 0.16)],
           "a_z": [(0.4, 27), (None, 0.89), (None, 0.35), (None, 0.22), (None, 0.16)]},
}


# --------------------------------------------------------------------------- positions


def positions(rng: np.random.Generator, n: int, law: str) -> np.ndarray:
    """(n, 3) unit gravity directions in the instrument frame.

    ``sphere``: uniform over the sphere (uniform over the solid angle).
    ``angles``: pitch uniform in [-90, 90] deg and roll uniform in [-180, 180] deg, the
    paper's g = (sin th, cos th cos ga, -cos th sin ga) (eq. 18 convention): dense near +-X.
    """
    if law == "sphere":
        v = rng.normal(size=(n, 3))
        return v / np.linalg.norm(v, axis=1, keepdims=True)
    th = rng.uniform(-np.pi / 2, np.pi / 2, n)
    ga = rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([np.sin(th), np.cos(th) * np.cos(ga), -np.cos(th) * np.sin(ga)])


# --------------------------------------------------------------------------- the paper's estimator


def frame(g_y: np.ndarray, g_x: np.ndarray) -> np.ndarray:
    """Rotation R with R g_y along +Y and R g_x in the XY half-plane x > 0: eqs. (18)-(19)
    (roll, pitch from the Y-up reading, heading from the X-up reading) without angle wrap."""
    r_y = g_y / np.linalg.norm(g_y)
    r_z = np.cross(g_x, r_y)
    r_z /= np.linalg.norm(r_z)
    return np.vstack([np.cross(r_y, r_z), r_y, r_z])


def estimate(y: np.ndarray, y_yup: np.ndarray, y_xup: np.ndarray,
             beta_from: str = "reference") -> tuple[np.ndarray, np.ndarray]:
    """Correction matrix (3, 3) and bias (3,) from positions ``y`` (n, 3) and references.

    ``beta_from="reference"``: the paper's scale 1/|g_hat| of the Y-up reading (eq. 18);
    ``"radius"``: 1/rho, the radius the D33 = 0 fit leaves (rho^2 = 1 + b^T D0 b).
    """
    x1, x2, x3 = y.T
    V = np.column_stack([x1 * x1, 2 * x1 * x2, x2 * x2, 2 * x1 * x3, 2 * x2 * x3, x3 * x3,
                         2 * x1, 2 * x2, 2 * x3])  # Eq. (10)-(11), D33 = 0
    d, *_ = np.linalg.lstsq(V, np.ones(len(y)), rcond=None)  # Eq. (12)
    D0 = np.array([[d[0], d[1], d[3]], [d[1], d[2], d[4]], [d[3], d[4], d[5]]])
    b = -np.linalg.solve(D0, d[6:9])  # Eq. (13)
    L = np.linalg.cholesky(D0)  # Eq. (15)
    g = L.T @ (y_yup - b)  # Eq. (17)
    beta = 1.0 / np.linalg.norm(g)  # Eq. (18)
    if beta_from == "radius":
        beta = 1.0 / np.sqrt(1.0 + b @ D0 @ b)
    R = frame(g, L.T @ (y_xup - b))  # Eqs. (18)-(19)
    return beta * R @ L.T, b  # Eq. (20)


def monte_carlo(n: int, sets: int, law: str, rng: np.random.Generator, ref_sigma: float,
                beta_from: str = "reference") -> dict[str, np.ndarray]:
    """Errors in mg over ``sets`` trials: bias (sets, 3), corrected g along OX and OZ (sets, 3)."""
    out = {"b": [], "ox": [], "oz": [], "oy": [], "failed": 0}
    y_ox, y_oy, y_oz = M_A @ E[0] + B, M_A @ E[1] + B, M_A @ E[2] + B
    for _ in range(sets):
        x = positions(rng, n, law)
        y = x @ M_A.T + B + rng.normal(0, SIGMA, (n, 3))
        ry = y_oy + rng.normal(0, ref_sigma, 3)
        rx = y_ox + rng.normal(0, ref_sigma, 3)
        try:
            M, b = estimate(y, ry, rx, beta_from)
        except np.linalg.LinAlgError:  # D0 not positive definite: a failed calibration
            out["failed"] += 1
            continue
        out["b"].append((b - B) * 1e3)
        out["ox"].append((M @ (y_ox - b) - E[0]) * 1e3)
        out["oy"].append((M @ (y_oy - b) - E[1]) * 1e3)
        out["oz"].append((M @ (y_oz - b) - E[2]) * 1e3)
    return {k: (np.array(v) if k != "failed" else v) for k, v in out.items()}


# --------------------------------------------------------------------------- Cramer-Rao bound


def _unpack(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return theta[:9].reshape(3, 3), theta[9:]


def fisher_per_position(law: str, samples: int = 20000) -> np.ndarray:
    """Mean (12, 12) Fisher information of one position (sigma = 1), orientation profiled out."""
    x = positions(np.random.default_rng(12345), samples, law)
    F = np.zeros((12, 12))
    for xi in x:
        J = np.zeros((3, 12))
        for i in range(3):
            J[i, 3 * i:3 * i + 3] = xi
        J[:, 9:] = np.eye(3)
        t1 = np.cross(xi, [1.0, 0, 0] if abs(xi[0]) < 0.9 else [0, 1.0, 0])
        t1 /= np.linalg.norm(t1)
        N = M_A @ np.column_stack([t1, np.cross(xi, t1)])  # d y / d orientation (nuisance)
        P = np.eye(3) - N @ np.linalg.solve(N.T @ N, N.T)
        F += J.T @ P @ J
    return F / samples


def _num_jac(f, theta: np.ndarray, h: float = 1e-7) -> np.ndarray:
    f0 = np.atleast_1d(f(theta))
    J = np.empty((len(f0), len(theta)))
    for i in range(len(theta)):
        tp = theta.copy()
        tp[i] += h
        J[:, i] = (np.atleast_1d(f(tp)) - f0) / h
    return J


def crb_halfwidths(F1: np.ndarray, n: int) -> dict[str, np.ndarray]:
    """1.96 sqrt(CRB) in mg of the bias and of the corrected g along OX and OZ (3 each)."""
    theta0 = np.concatenate([M_A.ravel(), B])
    y_ox, y_oy, y_oz = M_A @ E[0] + B, M_A @ E[1] + B, M_A @ E[2] + B

    def corrected(theta, y):
        S, b = _unpack(theta)
        return np.linalg.solve(S, y - b)

    def constraints(theta):  # the paper's use of the references (eqs. 17-19)
        return np.concatenate([corrected(theta, y_oy) - E[1], corrected(theta, y_ox)[2:]])

    H = _num_jac(constraints, theta0)
    U = np.linalg.svd(H)[2][H.shape[0]:].T  # (12, 8) null space of the constraints
    F = n * F1 / SIGMA**2
    C = U @ np.linalg.inv(U.T @ F @ U) @ U.T
    out = {}
    for key, g in (("b", lambda th: th[9:]), ("ox", lambda th: corrected(th, y_ox)),
                   ("oz", lambda th: corrected(th, y_oz))):
        J = _num_jac(g, theta0)
        out[key] = 1.96 * np.sqrt(np.clip(np.diag(J @ C @ J.T), 0.0, None)) * 1e3
    return out


# --------------------------------------------------------------------------- report


def _stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, 1.96 std, and the half-width of the central 95 % (percentiles) per column."""
    lo, hi = np.percentile(a, [2.5, 97.5], axis=0)
    return a.mean(axis=0), 1.96 * a.std(axis=0, ddof=1), (hi - lo) / 2


def _paper(cell: tuple) -> str:
    mean, hw = cell
    m = "" if mean is None else f"{mean:+.3g}"
    h = "" if hw is None else f"±{hw:.3g}"
    return (m + " " + h).strip()


def cross_check(rng: np.random.Generator, sets: int = 20, n: int = 200) -> None:
    """The same sets through imupipe's own method-A ellipsoid fit (imupipe.solvers), if present."""
    try:
        from imupipe.solvers.ellipsoid_cholesky import fit_ellipsoid
    except ImportError as exc:
        print(f"\n(imupipe.solvers.ellipsoid_cholesky not importable: {exc}; no cross-check)")
        return
    worst = 0.0
    for _ in range(sets):
        y = positions(rng, n, "sphere") @ M_A.T + B + rng.normal(0, SIGMA, (n, 3))
        _, b = estimate(y, M_A @ E[1] + B, M_A @ E[0] + B)
        shape = fit_ellipsoid(y, "accel", min_coverage=0.0)
        worst = max(worst, float(np.abs(shape.b * shape.scale - b).max()))
    print(f"\n=== cross-check: imupipe.solvers.ellipsoid_cholesky.fit_ellipsoid on {sets} sets of N = {n} "
          f"gives the bench's bias to {worst * 1e3:.1e} mg")


FINDINGS = """
=== why the reproduction and the paper differ
1. Position law. "Uniform over the full solid angle" read as uniform on the sphere gives equal
   bias widths on the three axes; the paper's Table 1 has b_x clearly narrower than b_y, b_z
   (0.08 vs 0.14 / 0.13 at N = 200). Drawing pitch and roll uniformly in angle (the paper's
   eq. 18 parametrisation of g) puts more positions near +-X and reproduces that asymmetry and
   the OX rows better (rms log-ratio to the paper above): the paper most likely drew angles.
2. Means. The paper's means of +0.04..0.06 mg (Table 1, N = 200 and 500, all axes) are 7-20
   standard errors of a 100-set mean from zero; the stated model gives means within MC noise
   (the LS bias from noise in the regressors is O(sigma^2) ~ 1e-4 mg). Not reproducible from
   the stated model: a property of the paper's noise generator or of reused draws.
3. N = 10 (9 unknowns): the error distribution is heavy tailed, so a 95 % interval from 100
   sets varies several-fold between repetitions (line below); the paper's +-15..41 mg lie at
   the upper end of that spread.
4. OY and OX z rows. The references fix the rotation exactly in this bench (TRIAD form of
   eqs. 18-19), so corrected g along OY is exact to rounding and the z component along OX is 0;
   the paper's 0.003 mg / -0.001 mg are residues of its Euler-angle arithmetic.
5. Efficiency. Bias and cross-axis cells sit at or near (within ~20 %) the Cramer-Rao bound. The diagonal cells
   (OX a_x, OZ a_z) are ~1.5x the bound: eq. (18) takes the scale from the one Y-up reading
   and discards the radius the N positions determine; taking beta = 1/rho instead reaches the
   bound (lines above).
"""


LAWS = {"sphere": "uniform over the sphere", "angles": "pitch and roll angles uniform (dense near +-X)"}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ref-sigma-mg", type=float, default=0.0,
                    help="noise of the reference readings (paper: exact; 0.5 = one raw sample)")
    args = ap.parse_args(argv)
    print(__doc__.split("\n\n")[0])
    print(f"sets = {args.sets}, seed = {args.seed}, sigma = {SIGMA * 1e3} mg, reference noise = "
          f"{args.ref_sigma_mg} mg.\nCells: mean ± 1.96 std | ± half-width of the central 95 % "
          "(percentiles) | paper | Cramer-Rao ± 1.96 sqrt(CRB)   (all mg)")
    print(f"raw g along OX (the paper's N = 0 column, g): {np.round(M_A @ E[0] + B, 4)}; "
          f"along OZ: {np.round(M_A @ E[2] + B, 4)}")
    ratios: dict[str, list[float]] = {}
    for law, what in LAWS.items():
        F1 = fisher_per_position(law)
        rng = np.random.default_rng([args.seed, 0 if law == "sphere" else 1])
        results = {n: monte_carlo(n, args.sets, law, rng, args.ref_sigma_mg * 1e-3) for n in NS}
        crbs = {n: crb_halfwidths(F1, n) for n in NS}
        ratios[law] = []
        print(f"\n=== positions: {law} ({what})")
        for table, key, title in (("T1", "b", "Table 1: bias error"),
                                  ("T2", "ox", "Table 2: corrected g along OX, error"),
                                  ("T3", "oz", "Table 3: corrected g along OZ, error")):
            print(f"\n{title} [mg]")
            for i, row in enumerate(PAPER[table]):
                print(f"  {row}")
                for j, n in enumerate(NS):
                    mean, sd196, pct = _stats(results[n][key])
                    fail = f"  ({results[n]['failed']} failed)" if results[n]["failed"] else ""
                    paper_hw = PAPER[table][row][j][1]
                    if n >= 50 and paper_hw and paper_hw > 0.02:
                        ratios[law].append(sd196[i] / paper_hw)
                    print(f"    N={n:5d}: {mean[i]:+8.3f} ± {sd196[i]:7.3f} | ± {pct[i]:7.3f} | paper "
                          f"{_paper(PAPER[table][row][j]):>14s} | CRB ± {crbs[n][key][i]:7.3f}{fail}")
        oy = np.abs(results[200]["oy"]).max()
        print(f"\n  corrected g along OY, N = 200: max |error| {oy:.1e} mg (the paper: typically 0.003 mg)")
    print("\n=== agreement with the paper, N >= 50 (ratio of our 1.96 std to the paper's half-width)")
    for law, r in ratios.items():
        lr = np.log(r)
        print(f"  {law:7s}: geometric mean {np.exp(lr.mean()):.2f}, rms log-ratio {np.sqrt(np.mean(lr**2)):.2f}, "
              f"cells {len(r)}")
    print(f"  sampling: a 95 % half-width from {args.sets} sets is itself uncertain by about "
          f"{100 / np.sqrt(2 * (args.sets - 1)):.0f} % (1 sigma, Gaussian case)")
    print("\n=== the paper's scale (eq. 18) against the fitted radius, uniform sphere: OX a_x and OZ a_z [mg]")
    F1 = fisher_per_position("sphere")
    for n in (200, 1000):
        cells = []
        for beta_from in ("reference", "radius"):
            r = monte_carlo(n, 300, "sphere", np.random.default_rng([args.seed, 5, n]), 0.0, beta_from)
            cells.append(f"{beta_from}: ±{_stats(r['ox'])[1][0]:.3f} / ±{_stats(r['oz'])[1][2]:.3f}")
        crb = crb_halfwidths(F1, n)
        print(f"  N={n:5d} (300 sets)  {'   '.join(cells)}   CRB ±{crb['ox'][0]:.3f} / ±{crb['oz'][2]:.3f}")
    print(FINDINGS)
    cross_check(np.random.default_rng([args.seed, 9]))
    rng = np.random.default_rng([args.seed, 7])
    hw = [_stats(monte_carlo(10, args.sets, "angles", rng, 0.0)["b"])[1][0] for _ in range(20)]
    print(f"\n=== N = 10 is nearly singular (9 unknowns): 20 repetitions of the {args.sets}-set experiment give "
          f"b_x 95 % half-widths from {min(hw):.1f} to {max(hw):.1f} mg (median {np.median(hw):.1f}); "
          "the paper's ±17 mg is one draw of this heavy-tailed statistic")


if __name__ == "__main__":
    main()

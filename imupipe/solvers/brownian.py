"""A bias random walk seen through interval averages, in linear time.

A bias that wanders as a Wiener process ``w(t)`` of intensity ``q`` (its variance
grows by ``q`` per second) is seen by each rest as its average over the rest's
interval ``[a, b]``. Exactly::

    avg_[a,b] w = (w(a) + w(b)) / 2 + e,     e ~ N(0, q (b - a) / 12) independent of w at any
                                              boundary (the Brownian bridge's average)

so the walk needs states only at interval boundaries, joined by independent
increments ``w(t_k+1) - w(t_k) ~ N(0, q (t_k+1 - t_k))``: a chain whose
precision is banded. ``imupipe.diagnosis.forward`` carries those states as
nuisance unknowns of the joint fit; here the same representation gives the
restricted likelihood (REML) of ``q`` in linear time (banded Cholesky), to pick
the walk's intensity from the rests before the fit.

The level of the walk is free (it is the bias itself): the first boundary's
state is pinned at zero and the regressors ``X`` of the REML hold the level, so
only contrasts matter -- the estimate equals that of any other convention for the
walk's level (e.g. centred on the session).
"""

from __future__ import annotations

import numpy as np

_GRID = np.linspace(-4.0, 10.0, 15)  # log10 of q L / (median white variance of a mean)
_NU_GRID = np.linspace(-1.0, 5.0, 7)  # log10 of the extra rest scatter / the same
MIN_LR = 2.71  # -2 log likelihood ratio for q > 0: 5 % false alarms (boundary, 1 parameter)


def boundaries(t_start: np.ndarray, t_end: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The walk's state times and, per interval, the indices of its two boundary states.

    Returns ``times`` (k,) sorted unique boundary times (the first is the pinned origin),
    ``ia``/``ib`` (n,) indices into ``times`` of each interval's start and end.
    """
    order = np.argsort(t_start)
    if np.any(t_end <= t_start) or np.any(t_start[order][1:] < t_end[order][:-1]):
        raise ValueError("walk intervals must have positive length and must not overlap")
    times = np.unique(np.concatenate([t_start, t_end]))
    return times, np.searchsorted(times, t_start), np.searchsorted(times, t_end)


def _banded_add(ab: np.ndarray, i: np.ndarray, j: np.ndarray, v: np.ndarray) -> None:
    """Add ``v`` at (i, j) with i >= j into lower banded storage ``ab`` (u+1, n); no (i, j) twice
    in one call (a plain in-place add: ``np.add.at``, which allows repeats, is slower)."""
    ab[i - j, j] += v


def _precision(times: np.ndarray, ia: np.ndarray, ib: np.ndarray, H: np.ndarray, dvar: np.ndarray,
               q: float) -> tuple[np.ndarray, int]:
    """Banded ``M = Lambda / q + H^T D^-1 H`` over the states ``times[1:]`` x ``D`` dims
    (``H`` (n, D) projection of each observation, ``dvar`` (n,) its white variance)."""
    D = H.shape[1]
    k = len(times) - 1  # states after the pinned origin
    u = 2 * D - 1
    ab = np.zeros((u + 1, k * D))
    dt = np.diff(times)
    w = 1.0 / (q * dt)  # (k,) increment precisions: increment s joins state s-1 and s
    for d in range(D):
        s = np.arange(k)
        _banded_add(ab, s * D + d, s * D + d, w)
        _banded_add(ab, s[:-1] * D + d, s[:-1] * D + d, w[1:])
        _banded_add(ab, s[1:] * D + d, s[:-1] * D + d, -w[1:])
    hw = H / np.sqrt(dvar)[:, None] / 2.0  # (n, D): each observation touches two states
    for a, b in ((ia, ia), (ib, ib), (ib, ia)):  # (row state, col state), row >= col
        keep = (a > 0) & (b > 0)
        for d1 in range(D):
            for d2 in range(D):
                r = (a[keep] - 1) * D + d1
                c = (b[keep] - 1) * D + d2
                low = r >= c
                if a is b and d1 < d2:
                    continue
                v = hw[keep, d1] * hw[keep, d2]
                _banded_add(ab, r[low], c[low], v[low])
    return ab, u


def _apply_H(H: np.ndarray, ia: np.ndarray, ib: np.ndarray, x: np.ndarray, D: int) -> np.ndarray:
    """``H_map x``: (n, m) the observations' averages of state vectors ``x`` (k D, m)."""
    x = np.vstack([np.zeros((D, x.shape[1])), x])  # the pinned origin
    xa = x.reshape(-1, D, x.shape[1])[ia]
    xb = x.reshape(-1, D, x.shape[1])[ib]
    return 0.5 * np.einsum("nd,ndm->nm", H, xa + xb)


def _apply_Ht(H: np.ndarray, ia: np.ndarray, ib: np.ndarray, y: np.ndarray, k: int) -> np.ndarray:
    """The transpose of ``_apply_H``: (k D, m)."""
    D = H.shape[1]
    out = np.zeros((k + 1, D, y.shape[1]))
    contrib = 0.5 * np.einsum("nd,nm->ndm", H, y)
    out[ia] += contrib  # no index twice: intervals do not overlap (``boundaries``)
    out[ib] += contrib
    return out[1:].reshape(k * D, y.shape[1])


def reml_cost(q: float, t_start: np.ndarray, t_end: np.ndarray, r: np.ndarray, var: np.ndarray,
              X: np.ndarray, H: np.ndarray | None = None, bounds: tuple | None = None) -> float:
    """-2 log restricted likelihood (up to a constant) of interval averages ``r`` (n,) with
    white variances ``var`` (n,), a walk of intensity ``q`` projected by ``H`` (n, D) (default
    1-D), and the regressors ``X`` (n, p) profiled out. ``q = 0``: white noise only.
    ``bounds``: ``boundaries(t_start, t_end)``, when the caller has them."""
    n = len(r)
    H = np.ones((n, 1)) if H is None else np.asarray(H, float)
    length = t_end - t_start
    dvar = var + q * length / 12.0 * np.sum(H * H, axis=1)
    Dinv = 1.0 / dvar
    A = np.column_stack([r, X])
    if q <= 0:
        VA = A * Dinv[:, None]
        logdet_V = float(np.log(dvar).sum())
    else:
        times, ia, ib = boundaries(t_start, t_end) if bounds is None else bounds
        Dd = H.shape[1]
        ab, _ = _precision(times, ia, ib, H, dvar, q)
        # scipy's cholesky_banded and cho_solve_banded, called on LAPACK directly: a walk's
        # intensity takes hundreds of these small solves, and scipy's checks cost as much.
        # Imported here: registering the solvers (joint_ml imports this module) stays free of
        # scipy.linalg, which pipelines without the joint fit never need (~0.15 s)
        from scipy.linalg.lapack import dpbtrf, dpbtrs

        from .blocktri import finite

        cb, info = dpbtrf(finite(ab), lower=1)
        if info > 0:  # not positive definite
            return np.inf
        if info < 0:
            raise ValueError(f"pbtrf: illegal argument {-info}")
        k = len(times) - 1
        HtDA = _apply_Ht(H, ia, ib, A * Dinv[:, None], k)
        Z, info = dpbtrs(cb, finite(HtDA), lower=1)
        if info:
            raise ValueError(f"pbtrs: illegal argument {-info}")
        VA = A * Dinv[:, None] - _apply_H(H, ia, ib, Z, Dd) * Dinv[:, None]
        # log|V| = log|D| + log|M| + log|q Lambda^-1| ; |Lambda^-1| = prod(dt) per dim
        logdet_V = float(np.log(dvar).sum() + 2 * np.log(cb[0]).sum()
                         + Dd * np.log(q * np.diff(times)).sum())
    G = A.T @ VA  # [[r'V^-1 r, r'V^-1 X], [X'V^-1 r, X'V^-1 X]]
    XVX = G[1:, 1:]
    sign, logdet_X = np.linalg.slogdet(XVX)
    if sign <= 0:
        return np.inf
    quad = G[0, 0] - G[0, 1:] @ np.linalg.solve(XVX, G[1:, 0])
    return logdet_V + logdet_X + float(quad)


def estimate_intensity(t_start: np.ndarray, t_end: np.ndarray, resid: np.ndarray, var: np.ndarray,
                       X: np.ndarray, H: np.ndarray | None = None, min_lr: float = MIN_LR) -> tuple[float, float]:
    """REML intensity ``q`` of a walk, and the extra scatter ``nu`` that is NOT time-correlated.

    ``resid`` (n, a): ``a`` independent series of interval averages (e.g. the three gyro axes)
    sharing one ``q`` (pooled: a per-axis estimate from one session scatters by a factor 2);
    ``var`` (n, a) their white variances; ``X`` (n, p) regressors profiled out (a constant
    column at least); ``H`` (n, D) projects a D-dimensional walk onto a single series (a = 1).
    ``q = 0`` unless the walk improves the restricted likelihood by ``min_lr`` (default 5 % false
    alarms: a walk detected; 0, the likelihood's maximum: a nuisance estimated).
    """
    resid = np.asarray(resid, float).reshape(len(resid), -1)
    var = np.asarray(var, float).reshape(len(var), -1)
    n = len(resid)
    span = float(np.ptp(np.r_[t_start, t_end])) if n else 0.0
    if n < 4 or span <= 0:
        return 0.0, 0.0
    U, sv, _ = np.linalg.svd(X, full_matrices=False)
    X = U[:, sv > 1e-8 * sv[0]]  # the same column space, without collinear regressors

    bounds = boundaries(t_start, t_end)

    def cost(q: float, nu: float) -> float:
        return sum(reml_cost(q, t_start, t_end, resid[:, a], var[:, a] + nu, X, H, bounds)
                   for a in range(resid.shape[1]))

    v0 = float(np.median(var))
    qs = np.r_[0.0, v0 / span * 10.0**_GRID]
    nus = np.r_[0.0, v0 * 10.0**_NU_GRID]
    C = np.array([[cost(q, nu) for nu in nus] for q in qs])
    i, j = np.unravel_index(np.argmin(C), C.shape)
    nu = float(nus[j])
    if i == 0 or C[0].min() - C[i, j] < min_lr:
        return 0.0, float(nus[np.argmin(C[0])])
    x = np.log10(qs[i] * span / v0)
    x, fx = bounded_minimum(lambda x: cost(v0 / span * 10.0**x, nu), x - 0.5, x + 0.5, xatol=0.01)
    q = v0 / span * 10.0 ** float(x) if fx < C[i, j] else float(qs[i])
    return q, nu


def bounded_minimum(f, lo: float, hi: float, xatol: float = 1e-5, maxiter: int = 500
                    ) -> tuple[float, float]:
    """``(x, f(x))`` at a minimum of ``f`` on ``[lo, hi]``: Brent's bounded method, step for step
    SciPy's ``minimize_scalar(method="bounded")`` (the same points and result, tested). Here,
    not imported: ``scipy.optimize`` costs ~0.2 s and ~17 MiB resident to a run that needs
    nothing else from it (``bench/scaling.py --without-map``)."""
    sqrt_eps = np.sqrt(2.2e-16)
    golden_mean = 0.5 * (3.0 - np.sqrt(5.0))
    a, b = lo, hi
    fulc = a + golden_mean * (b - a)
    nfc, xf = fulc, fulc
    rat = e = 0.0
    fx = f(xf)
    num = 1
    ffulc = fnfc = fx
    xm = 0.5 * (a + b)
    tol1 = sqrt_eps * np.abs(xf) + xatol / 3.0
    tol2 = 2.0 * tol1
    while np.abs(xf - xm) > (tol2 - 0.5 * (b - a)):
        golden = True
        if np.abs(e) > tol1:  # a parabola through the three best points
            golden = False
            r = (xf - nfc) * (fx - ffulc)
            q = (xf - fulc) * (fx - fnfc)
            p = (xf - fulc) * q - (xf - nfc) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = np.abs(q)
            r = e
            e = rat
            if np.abs(p) < np.abs(0.5 * q * r) and q * (a - xf) < p < q * (b - xf):  # acceptable
                rat = (p + 0.0) / q
                x = xf + rat
                if (x - a) < tol2 or (b - x) < tol2:
                    rat = tol1 * (np.sign(xm - xf) + ((xm - xf) == 0))
            else:
                golden = True
        if golden:  # a golden-section step
            e = (a if xf >= xm else b) - xf
            rat = golden_mean * e
        x = xf + (np.sign(rat) + (rat == 0)) * np.maximum(np.abs(rat), tol1)
        fu = f(x)
        num += 1
        if fu <= fx:
            if x >= xf:
                a = xf
            else:
                b = xf
            fulc, ffulc = nfc, fnfc
            nfc, fnfc = xf, fx
            xf, fx = x, fu
        else:
            if x < xf:
                a = x
            else:
                b = x
            if fu <= fnfc or nfc == xf:
                fulc, ffulc = nfc, fnfc
                nfc, fnfc = x, fu
            elif fu <= ffulc or fulc == xf or fulc == nfc:
                fulc, ffulc = x, fu
        xm = 0.5 * (a + b)
        tol1 = sqrt_eps * np.abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1
        if num >= maxiter:
            break
    return xf, fx

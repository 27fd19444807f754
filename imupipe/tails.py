"""Tail probabilities and quantiles of the chi-square, normal, Student t and F distributions.

The same values as ``scipy.stats`` (the same ``scipy.special`` functions, the same answers
outside the support: 1 below zero, NaN for dof <= 0) without importing ``scipy.stats``,
which costs a process about 0.25 s (``scipy.signal``, which imports it, 0.15 s more).
``scipy.special`` itself (0.1-0.2 s) is imported by the functions that call it: the F tail,
a finite sum for the even numerator the verdict's drift test has, needs none.
"""

from __future__ import annotations

import numpy as np


def _special():
    from scipy import special

    return special


def chi2_sf(x, dof):
    """P(X > x) for X ~ chi2(dof)."""
    x, dof = np.asarray(x, float), np.asarray(dof, float)
    with np.errstate(invalid="ignore"):
        p = np.where(x <= 0, 1.0, _special().chdtrc(dof, np.maximum(x, 0)))
    return _scalar(np.where(dof > 0, p, np.nan))


def chi2_isf(p, dof):
    """x with P(X > x) = p for X ~ chi2(dof)."""
    p, dof = np.asarray(p, float), np.asarray(dof, float)
    return _scalar(np.where((dof > 0) & (p >= 0) & (p <= 1), _special().chdtri(dof, np.clip(p, 0, 1)), np.nan))


def chi2_ppf(p, dof):
    """x with P(X <= x) = p for X ~ chi2(dof)."""
    p, dof = np.asarray(p, float), np.asarray(dof, float)
    ok = (dof > 0) & (p >= 0) & (p <= 1)
    return _scalar(np.where(ok, 2 * _special().gammaincinv(np.where(ok, dof, 1) / 2, np.clip(p, 0, 1)), np.nan))


def norm_sf(z):
    """P(Z > z) for a standard normal Z."""
    return _scalar(_special().ndtr(-np.asarray(z, float)))


def norm_isf(p):
    """z with P(Z > z) = p for a standard normal Z."""
    return _scalar(-_special().ndtri(np.asarray(p, float)))


def t_sf(t, dof):
    """P(T > t) for T ~ Student t(dof)."""
    t, dof = np.asarray(t, float), np.asarray(dof, float)
    return _scalar(np.where(dof > 0, _special().stdtr(np.where(dof > 0, dof, 1), -t), np.nan))


def f_sf(x: float, d1: int, d2: float) -> float:
    """P(F > x) for F ~ F(d1, d2) with an even ``d1``: ``I_y(d2/2, d1/2)``, ``y = d2 / (d2 + d1 x)``,
    is then a finite sum (``scipy.stats.f.sf`` to 1e-11 relative, not bit for bit)."""
    if d1 % 2:
        raise ValueError(f"f_sf: d1 = {d1} must be even")
    a, y = 0.5 * d2, d2 / (d2 + d1 * max(x, 0.0))
    term = total = 1.0
    for k in range(1, d1 // 2):
        term *= (a + k - 1) / k * (1.0 - y)
        total += term
    return float(y**a * total)


def _scalar(a: np.ndarray):
    return a[()] if a.ndim == 0 else a

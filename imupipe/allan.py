"""The recording's own noise model: overlapping Allan deviation of rests, its five-term fit,
and the effective sample size of a rest's mean under that (coloured) noise.

Allan variance of a rate (IEEE Std 952-1997, Annex C; NIST SP 1065), per axis, in the
triad's units (rad/s, m/s^2, T), ``tau`` in s::

    avar(tau) = 3 Q^2 / tau^2  +  N^2 / tau  +  (2 ln2 / pi) B^2  +  K^2 tau / 3  +  R^2 tau^2 / 2

``Q`` quantisation (of an integrated output: units*s), ``N`` white noise density
(units/sqrt(Hz), Kalibr's ``*_noise_density``), ``B`` bias instability (units), ``K``
rate random walk (units/s/sqrt(Hz), Kalibr's ``*_random_walk``, the simulator's
``bias_rw``), ``R`` rate ramp (units/s). A per-sample white sigma ``s`` at rate ``f`` is ``N = s/sqrt(f)``
(rounding a sample to a quantum ``q`` adds ``q^2/12`` to ``s^2``: it is white, not ``Q``).
Rests are pooled per tau, weighted by their equivalent degrees of freedom.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import SolverError, require

TERMS = ("quantisation", "noise_density", "bias_instability", "random_walk", "rate_ramp")
_B = 2 * np.log(2) / np.pi


def basis(tau: np.ndarray) -> np.ndarray:
    """(n, 5) Allan variance of each term per unit squared coefficient, at ``tau`` (n,) s."""
    tau = np.asarray(tau, float)
    return np.column_stack([3 / tau**2, 1 / tau, np.full_like(tau, _B), tau / 3, tau**2 / 2])


def edf_white(n: int, m: np.ndarray) -> np.ndarray:
    """Equivalent degrees of freedom of the overlapping Allan variance at ``m`` samples per tau,
    white frequency noise, ``n`` samples (NIST SP 1065, Table 5, after Howe et al.)."""
    m = np.asarray(m, float)
    return np.maximum((3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m**2 / (4 * m**2 + 5), 1.0)


@dataclass(frozen=True)
class AllanCurve:
    """Pooled overlapping Allan deviation of one axis: ``tau`` (k,) s, ``adev`` (k,) units,
    ``edf`` (k,) equivalent degrees of freedom, ``terms`` (k,) overlapping differences."""

    tau: np.ndarray
    adev: np.ndarray
    edf: np.ndarray
    terms: np.ndarray

    @property
    def adev_err(self) -> np.ndarray:
        """(k,) 1-sigma of ``adev`` (relative sd of a variance sqrt(2/edf), halved)."""
        return self.adev / np.sqrt(2 * self.edf)


def allan_curve(segments: list[np.ndarray], rate_hz: float, per_decade: int = 8,
                max_fraction: float = 1 / 3) -> AllanCurve:
    """Pooled OADEV of ``segments`` (each (n_i,) samples of one axis at ``rate_hz``): taus
    ``per_decade`` log-spaced from one sample to ``max_fraction`` of the longest segment."""
    allantools = require("allantools", "noise")
    longest = max(len(s) for s in segments)
    if longest < 8:
        raise SolverError(f"noise: the longest rest has {longest} samples; Allan deviation needs "
                          "at least 8 (record a longer still interval)")
    m_all = np.unique(np.round(np.logspace(0, np.log10(max(longest * max_fraction, 1.0)),
                                           int(per_decade * np.log10(max(longest * max_fraction, 10))) + 1)))
    m_all = m_all[m_all >= 1].astype(int)
    num, den, terms = np.zeros(len(m_all)), np.zeros(len(m_all)), np.zeros(len(m_all))
    for seg in segments:
        n = len(seg)
        ok = m_all <= max(int(n * max_fraction), 1)
        if not ok.any() or n < 8:
            continue
        taus, ad, _, ns = allantools.oadev(np.asarray(seg, float), rate=rate_hz, data_type="freq",
                                           taus=m_all[ok] / rate_hz)
        m = np.round(np.asarray(taus) * rate_hz).astype(int)
        idx = np.searchsorted(m_all, m)
        e = edf_white(n, m)
        num[idx] += e * np.asarray(ad) ** 2
        den[idx] += e
        terms[idx] += np.asarray(ns)
    keep = den > 0
    return AllanCurve(m_all[keep] / rate_hz, np.sqrt(num[keep] / den[keep]), den[keep], terms[keep])


@dataclass(frozen=True)
class NoiseFit:
    """Fitted terms (``TERMS`` -> value, units of the module doc) of one axis, with the curve."""

    coef: dict[str, float]
    curve: AllanCurve
    chi2_per_dof: float
    extra: dict = field(default_factory=dict)

    def avar(self, tau: np.ndarray) -> np.ndarray:
        c = np.array([self.coef[t] ** 2 for t in TERMS])
        return basis(np.atleast_1d(tau)) @ c

    def adev(self, tau: np.ndarray) -> np.ndarray:
        return np.sqrt(self.avar(tau))


def fit_curve(curve: AllanCurve, terms: tuple[str, ...] = TERMS, iterations: int = 3) -> NoiseFit:
    """Non-negative weighted least squares of the Allan variance on ``terms`` (others held at 0);
    weights from the model's own variance (sd of avar = avar sqrt(2/edf)), iterated."""
    # here, not at the top: a warm run loads this module and skips importing scipy.optimize
    from scipy.optimize import nnls

    cols = [TERMS.index(t) for t in terms]
    A = basis(curve.tau)[:, cols]
    y = curve.adev**2
    model = y.copy()
    for _ in range(iterations):
        sd = np.maximum(model, 1e-300) * np.sqrt(2 / curve.edf)
        c, _ = nnls(A / sd[:, None], y / sd)
        model = np.maximum(A @ c, 1e-300)
    sd = model * np.sqrt(2 / curve.edf)
    dof = max(len(y) - np.count_nonzero(c), 1)
    chi2 = float(np.sum(((y - model) / sd) ** 2) / dof)  # taus overlap: a guide, not a test
    coef = dict.fromkeys(TERMS, 0.0)
    coef.update({t: float(np.sqrt(v)) for t, v in zip(terms, c, strict=True)})
    return NoiseFit(coef, curve, chi2)


def avar_at(fit: NoiseFit, tau: np.ndarray) -> np.ndarray:
    """Allan variance at ``tau`` (n,) s: the measured curve (log-log interpolated) inside its
    range, the fit outside it (coloured noise the five terms miss, e.g. 4-8 Hz tremor, is kept
    where it was measured)."""
    tau = np.atleast_1d(np.asarray(tau, float))
    c = fit.curve
    out = fit.avar(tau)
    inside = (tau >= c.tau[0]) & (tau <= c.tau[-1])
    if inside.any() and len(c.tau) > 1:
        out[inside] = np.exp(np.interp(np.log(tau[inside]), np.log(c.tau), np.log(c.adev**2)))
    return out


def batch_variance_ratio(y: np.ndarray, batches: int = 8) -> np.ndarray | None:
    """(k,) per column of ``y`` (n, k): the variance of its ``batches`` batch means over what
    white noise would give them (1 for white noise; above 1 when neighbouring samples agree);
    None when a batch would hold fewer than 2 samples. Columns without spread give NaN."""
    m = len(y) // batches
    if m < 2:
        return None
    means = y[: m * batches].reshape(batches, m, -1).mean(1)
    white = y.var(0, ddof=1) / m
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(white > 0, means.var(0, ddof=1) / white, np.nan)


def effective_sample_size(var_sample: np.ndarray, duration_s: np.ndarray, count: np.ndarray,
                          fit: NoiseFit) -> np.ndarray:
    """(n,) samples of white noise that would give a rest's mean the variance it has under the
    measured noise: ``var_sample / avar(T)`` (the Allan variance at the rest's length stands
    for the variance of its mean; for white noise ``n_eff = n``), between 1 and the count
    (noise that averages out faster than white, a pure tone, is not credited)."""
    v = avar_at(fit, np.maximum(np.asarray(duration_s, float), 1e-9))
    n_eff = np.asarray(var_sample, float) / np.maximum(v, 1e-300)
    return np.clip(n_eff, 1.0, np.maximum(np.asarray(count, float), 1.0))

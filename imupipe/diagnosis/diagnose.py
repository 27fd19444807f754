"""``diagnosis.json``: findings the diagnosis stands behind, effects it cannot see, and why.

``diagnose(ev, map_doc, effects)`` tests every catalogue candidate (``select``), keeps the
significant ones with their fitted parameters, held-out RMS before and after and an
explanation; a cell of the residual map that stays flagged and that no accepted term's
sensor and regime covers becomes an ``unknown`` finding that says what it correlates with.
A significant term that does not predict held-out data significantly better (the z of the
predictive chi2's decrease below ``HELDOUT_Z``) is not a finding (``not_confirmed``).

A session's findings come from three families of tests: the catalogue's forward selection,
the structure cells left after the accepted terms, and the map's chi2/dof cells. ``q`` is
split among them (``FAMILY_SHARE``: Bonferroni across the families, Benjamini-Hochberg within
each), so that a session without omitted physics reports anything at most ``q`` of the time.
"""

from __future__ import annotations

import numpy as np

from ..effects.earth_rotation import EARTH_RATE
from .evaluate import Evaluation
from .library import structure_cells
from .residual_map import benjamini_hochberg, windows
from .select import (BLOCK_S, BOOT_DRAWS, EARTH_IMPLAUSIBLE, HELDOUT_Z, LONG_BLOCKS, Q_FDR, REVEAL, UNTESTED,
                     VISIBLE_MIN, Finding, candidates, examine, heldout, rigid_walks, select, theta_cov, triads)

AXES = ("x", "y", "z")
SD_DRAWS = 400  # draws carrying a term's covariance to its parameters' standard deviations
FAMILY_SHARE = {"catalogue": 0.5, "structure": 0.25, "map": 0.25}  # of q; the three sum to 1


def family_levels(q: float) -> dict[str, float]:
    """Each family's Benjamini-Hochberg level: ``q`` split by ``FAMILY_SHARE``."""
    return {family: q * share for family, share in FAMILY_SHARE.items()}


def map_unknown_cells(map_doc: dict | None, level: float) -> list[dict]:
    """The map's chi2/dof cells (its structure cells are tested given the findings instead)
    discovered by Benjamini-Hochberg at ``level`` (the map's own flags are at its ``fdr_q``)."""
    cells = [c for c in (map_doc or {}).get("cells", []) if c["variable"] != "structure"]
    found = benjamini_hochberg(np.array([c["p_value"] for c in cells]), level)
    return [c for c, f in zip(cells, found, strict=True) if f]


def noise_misfit(map_doc: dict | None, q: float = Q_FDR) -> frozenset[str]:
    """The sensors whose noise floor the map finds misfit: an ``all`` cell of theirs discovered
    at the map family's level (``select``'s long bootstrap blocks are for them)."""
    return frozenset(c["sensor"] for c in map_unknown_cells(map_doc, family_levels(q)["map"]) if c["variable"] == "all")


def diagnose(ev: Evaluation, map_doc: dict | None, effects: dict, session: str = "", q: float = Q_FDR,
             latitude_deg: float | None = None) -> dict:
    lin = ev.lin
    level = family_levels(q)
    rigid = rigid_walks(lin)
    tested = [examine(lin, c, rigid) for c in candidates(lin, ev.frame, effects)]
    misfit = noise_misfit(map_doc, q)
    rp, findings, not_confirmed, kept = catalogue_findings(lin, tested, effects, level["catalogue"],
                                                           latitude_deg=latitude_deg, misfit=misfit)
    # structure the accepted terms leave: the generic library tested conditionally on them
    given = np.hstack([f.tested.projected for f in kept]) if kept else None
    left = structure_cells(lin, given, rp, bootstrap=True, level=level["structure"])
    for cell, flag in zip(left, benjamini_hochberg(np.array([c.p_value for c in left]), level["structure"])):
        if flag and not any(u["sensor"] == cell.sensor and u["regime"] == cell.regime
                            for u in findings if u["effect"] == "unknown"):
            findings.append(_structure(cell))
    covered = {(f["sensor"], f["regime"]) for f in findings}
    for cell in map_unknown_cells(map_doc, level["map"]):
        regimes = {cell["regime"], "all"}
        if any((cell["sensor"], r) in covered for r in regimes):
            continue
        findings.append(_unknown(cell))
        covered.add((cell["sensor"], cell["regime"]))
    return {"session": session, "findings": findings, **coverage(tested, effects), "not_confirmed": not_confirmed,
            "fdr_q": q, "family_q": level,
            "method": "score tests against the fitted per-sample model (the larger p of chi-square and a wild "
                      f"bootstrap over {BLOCK_S:g}-s time blocks, {BOOT_DRAWS} draws; over {LONG_BLOCKS} spans of the "
                      "recording for a sensor whose noise floor the map finds misfit"
                      + (f": {', '.join(sorted(misfit))}" if misfit else "") + "), "
                      "Benjamini-Hochberg forward selection with a backward check, held-out proof by "
                      "blocked cross-validation (stretches of time, or rests and motions, each held out in "
                      "turn; the z of the predictive chi2's decrease); q split among the catalogue, the structure "
                      "cells and the map's cells (Bonferroni across, Benjamini-Hochberg within)"}


def catalogue_findings(lin, tested: list, effects: dict, q: float = Q_FDR, held_out=heldout,
                       latitude_deg: float | None = None, misfit: frozenset[str] = frozenset()
                       ) -> tuple[np.ndarray, list[dict], list[dict], list[Finding]]:
    """The selected catalogue terms (``select``, with the recording's latitude when known and the
    sensors whose noise floor misfits) that also predict held-out data better
    (``held_out(lin, rp, finding, others) -> select.HeldOut``): ``(rp, findings, not_confirmed,
    kept)``, ``rp`` the residual with the nominal model refitted."""
    rp, accepted = select(lin, tested, q, latitude_deg, misfit)
    findings, not_confirmed, kept = [], [], []
    for i, f in enumerate(accepted):
        doc = _finding(lin, rp, f, accepted[:i] + accepted[i + 1:], effects, held_out)
        rejects = f.tested.candidate.rejects
        unphysical = rejects(f.theta) if rejects else None  # e.g. a thermal lag the read-out makes
        if not unphysical and doc["heldout_z"] >= HELDOUT_Z:
            findings.append(_partial(doc, f.beyond) if f.beyond else _ambiguous(doc, f.rivals) if f.rivals else doc)
            kept.append(f)
        else:  # significant on the data it was fitted to, not better on data it was not: not stood behind
            not_confirmed.append({"effect": doc["effect"], "sensor": doc["sensor"], "regime": doc["regime"],
                                  "parameters": doc["parameters"], "significance": doc["significance"],
                                  "reason": unphysical or
                                  "held-out prediction did not improve significantly (RMS "
                                  f"{doc['heldout_rms_before']:.4g} -> {doc['heldout_rms_after']:.4g}, "
                                  f"z = {doc['heldout_z']:.2f} < {HELDOUT_Z})", **_heldout_fields(doc)})
    return rp, findings, not_confirmed, kept


def coverage(tested: list, effects: dict) -> dict:
    """``not_identifiable``, ``tested`` and ``untested`` of diagnosis.json."""
    seen = {(t.candidate.effect, t.candidate.sensor) for t in tested if t.visible >= VISIBLE_MIN}
    not_identifiable = []
    for t in tested:
        key = (t.candidate.effect, t.candidate.sensor)
        if t.visible >= VISIBLE_MIN or key in seen or any(
                n["effect"] == key[0] and n["sensor"] == key[1] for n in not_identifiable):
            continue
        not_identifiable.append({
            "effect": t.candidate.effect, "sensor": t.candidate.sensor,
            "biases": [name for name, _ in t.biases],
            "bias_per_unit_effect": {name: v for name, v in t.biases},
            "visible_fraction": t.visible,
            "reveal_with": REVEAL.get(t.candidate.effect, "a recording that excites this effect"),
        })
    tested_doc = []
    for t in tested:
        c = t.candidate
        tested_doc.append({"effect": c.effect, "sensor": c.sensor, "regime": c.regime, **c.fixed,
                           "parameters": c.names, "visible_fraction": t.visible, "minimum_detectable": t.mde,
                           "information": (t.projected.T @ t.projected).tolist()})
    present = {t.candidate.effect for t in tested}
    untested = [{"effect": e, "reason": why} for e, why in UNTESTED.items() if e in effects and e not in present]
    untested += [{"effect": e, "reason": "this recording has no rows its term acts on"}
                 for e in ("lever_arm", "accel_gyro_time_offset") if e in effects and e not in present]
    return {"not_identifiable": not_identifiable, "tested": tested_doc, "untested": untested}


def _finding(lin, rp: np.ndarray, f: Finding, others: list[Finding], effects: dict, held_out=heldout) -> dict:
    c = f.tested.candidate
    effect = c.effect
    if effect == "earth_rotation" and abs(f.theta[0]) > EARTH_IMPLAUSIBLE * EARTH_RATE:
        # a vertical rate Earth cannot make: the isotropic g-sensitivity it is indistinguishable from at rest
        effect = "gyro_g_sensitivity"

        def to_params(th: np.ndarray) -> dict:
            return {"G": (float(th[0]) / lin.model.g * np.eye(3)).tolist()}
    else:
        to_params = c.to_params
    params = {k: _json(v) for k, v in to_params(f.theta).items()}
    held = held_out(lin, rp, f, others)
    contrib = (f.tested.projected @ f.theta) ** 2
    rows = np.any(c.columns != 0, axis=1)
    where = windows(lin.rows.t[rows], contrib[rows])
    try:
        words = effects[effect].explain({k: v for k, v in params.items()})
    except Exception:  # noqa: BLE001 - a plugin's explain must not sink the diagnosis
        words = f"{effect}: {params}"
    return {
        "effect": effect, "sensor": c.sensor, "axes": list(AXES), "regime": c.regime,
        "windows": [[float(a), float(b)] for a, b in where],
        "parameters": params,
        "parameters_sd": _parameter_sd(rp, f, others, to_params),
        "significance": {"statistic": f.statistic, "p_value": f.p_value, "p_value_asymptotic": f.p_asymptotic,
                         "delta_bic": f.delta_bic, "bootstrap_draws": BOOT_DRAWS},
        "heldout_rms_before": held.rms_before, "heldout_rms_after": held.rms_after, "heldout_z": held.z,
        "heldout_chi2_n_before": _finite(held.chi2_n_before), "heldout_chi2_n_after": _finite(held.chi2_n_after),
        "visible_fraction": f.tested.visible,
        "explanation": (f"The {_readings(c.sensor)} residuals in the {c.regime} rows carry a term the nominal model "
                        f"cannot make (score chi2 {f.statistic:.1f} on {f.tested.projected.shape[1]} dof, "
                        f"p = {f.p_value:.2g}); modelled as {words} Held out: RMS {held.rms_before:.4g} -> "
                        f"{held.rms_after:.4g}" + (f", predictive chi2/n {held.chi2_n_before:.4f} -> "
                                                   f"{held.chi2_n_after:.4f}" if np.isfinite(held.chi2_n_after)
                                                   else "") + f" (improvement z = {held.z:.1f})."),
    }


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _parameter_sd(rp: np.ndarray, f: Finding, others: list[Finding], to_params, draws: int = SD_DRAWS) -> dict:
    """1-sigma of each numeric parameter: the term's covariance from the linearised joint fit with
    the other accepted terms (scaled by the affected rows' chi2/dof when above 1, as its test is),
    carried through ``to_params`` by ``draws`` seeded draws (exact for the linear maps most are)."""
    cov = theta_cov(rp, f, others)
    k = len(cov)
    w, V = np.linalg.eigh((cov + cov.T) / 2)
    sample = f.theta + (np.random.default_rng(0).standard_normal((draws, k)) * np.sqrt(np.clip(w, 0, None))) @ V.T
    out = {}
    for name, value in to_params(f.theta).items():
        try:
            np.asarray(value, float)
        except (TypeError, ValueError):
            continue  # a label (the sensor), not a number
        out[name] = _json(np.std([np.asarray(to_params(th)[name], float) for th in sample], axis=0))
    if f.dtheta_dtau is not None:  # a profiled time constant: its own sd (``select._profile``)
        out["tau_s"] = f.tau_sd
    return out


def _unknown_finding(sensor: str, axes: list, regime: str, windows: list, parameters: dict,
                     statistic: float, p_value: float, explanation: str) -> dict:
    """A finding no catalogue term explains: where, how strong, and what it correlates with (its
    ``description``, effects.md's parameter: the explanation)."""
    return {"effect": "unknown", "sensor": sensor, "axes": list(axes), "regime": regime,
            "windows": [list(w) for w in windows], "parameters": {"description": explanation, **parameters},
            "significance": {"statistic": statistic, "p_value": p_value, "delta_bic": None},
            "heldout_rms_before": None, "heldout_rms_after": None, "heldout_z": None,
            "explanation": explanation}


def _not_stood_behind(doc: dict, candidates: list[str], explanation: str) -> dict:
    """A confirmed term reported as an ``unknown`` naming ``candidates``, its fit and held-out kept."""
    out = _unknown_finding(
        doc["sensor"], doc["axes"], doc["regime"], doc["windows"],
        {"candidates": candidates, doc["effect"]: doc["parameters"]}, doc["significance"]["statistic"],
        doc["significance"]["p_value"], explanation)
    out.update(_heldout_fields(doc))
    return out


def _heldout_fields(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k.startswith("heldout_")}


def _ambiguous(doc: dict, rivals: list[str]) -> dict:
    """A confirmed term whose rivals explain the recording as well: an ``unknown`` naming each."""
    names = [doc["effect"], *rivals]
    reveal = "; ".join(f"{n}: {REVEAL[n]}" for n in names if n in REVEAL)
    return _not_stood_behind(
        doc, names,
        f"The {_readings(doc['sensor'])} residuals in the {doc['regime']} rows carry a term that {' or '.join(names)} "
        f"explains equally well on this recording (each significant in the other's place, neither "
        f"beyond the other): a naming trap it cannot resolve, so neither is stood behind. "
        f"To tell them apart: {reveal or 'a recording that excites them differently'}.")


def _partial(doc: dict, larger: str) -> dict:
    """A confirmed term a larger one outside the catalogue goes significantly beyond (``Finding.beyond``)."""
    return _not_stood_behind(
        doc, [doc["effect"]],
        f"{doc['effect']} explains part of the {_readings(doc['sensor'])} residuals in the {doc['regime']} rows, but "
        f"{larger}, outside the catalogue, goes significantly beyond it: the structure is not "
        f"{doc['effect']} alone, so it is not stood behind.")


def _unknown(cell: dict) -> dict:
    """From a flagged chi2/dof cell of the map."""
    var, (lo, hi) = cell["variable"], cell["range"]
    where = ("" if lo is None and hi is None else f"with {var} {lo} " if isinstance(lo, str)
             else f"with {var} in [{_edge(lo, '-inf')}, {_edge(hi, 'inf')}] ")
    return _unknown_finding(
        cell["sensor"], cell["axes"], cell["regime"], cell.get("windows", []), {}, cell["chi2"], cell["p_value"],
        f"The {cell['sensor']} {'/'.join(cell['axes'])} residuals in the {cell['regime']} rows "
        f"{where}have chi2/dof {cell['chi2_per_dof']:.2f} and no catalogue "
        "term explains them: look at those windows (an unmodelled disturbance, a knock, a "
        "vibrating support or physics outside the catalogue).")


def _readings(sensor: str) -> str:
    """Whose residuals a term of ``sensor`` moves, in words (``select.triads``)."""
    return " and ".join(triads(sensor))


def _edge(x: float | None, infinite: str) -> str:
    return infinite if x is None else f"{x:.3g}"


def _structure(cell) -> dict:
    """From a structure cell still significant given the accepted terms."""
    stable = (f"a sparse fit stable over half-samples of the recording keeps {_in_words(cell.stable)}"
              if cell.stable else "no signal is stable over half-samples of the recording")
    return _unknown_finding(
        cell.sensor, cell.axes, cell.regime, cell.windows, {"follows": cell.terms, "stable": cell.stable},
        cell.chi2, cell.p_value,
        f"The {cell.sensor} {'/'.join(cell.axes)} residuals in the {cell.regime} rows follow "
        f"signals the model already reconstructs (score chi2 {cell.chi2:.1f} on {cell.dof:g} "
        f"directions, p = {cell.p_value:.2g}) and no accepted catalogue term explains it; "
        f"strongest alone: {_in_words(cell.terms)}; {stable}.")


def _in_words(terms: list[dict]) -> str:
    return "; ".join(f"{t['signal']} on {t['output_axis']} ({t['coefficient']:.3g} {t['unit']}, t = {t['t']:.1f}"
                     + (f", chosen in {t['chosen']:.0%}" if "chosen" in t else "") + ")" for t in terms)


def _json(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (list, tuple)):
        return [_json(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v

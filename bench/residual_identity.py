"""The calibration's and the residual map's numbers on a fixed session, saved by one version of imupipe and
checked by another.

    python bench/residual_identity.py --save REF [--seed 0] [--protocol standard]
    python bench/residual_identity.py --check REF [--rtol 1e-9] [--floor-kernels Prescott,Nehalem,Sandybridge]

``--save`` simulates the session (``imupipe simulate``'s protocol and seed; the standard
protocol is the 30-minute session of ``bench/residual_cost.py``) into ``REF.d``, runs the
default pipeline on it; ``--check`` reruns the map stage
alone on a copy of ``REF.d``, whose cache holds the stages before it as they were saved (so
an upstream change, amplified by the fits' stopping rules, does not mask the map's own). Both
read what the map stage wrote: ``residuals.parquet`` (every sample's prediction, residual
and whitened residual, gravity, |omega|, |alpha|, ...) and ``residual_map.json`` (every
cell's and block's chi2, dof, p-value, events, change points). ``--save`` stores them as
``REF.npz`` and ``REF.json``; ``--check`` recomputes them with the imupipe this Python
imports and compares every number (relative to the value, or to its column's largest for
per-sample columns; p-values on ``-log10 p``; strings and shapes equal).

Not every number is determined to ``rtol`` (1e-9) by the code alone: the same code with
another of OpenBLAS's kernels (``OPENBLAS_CORETYPE``: what another CPU gives) moves the map's
per-sample columns by up to ~4e-9 and its chi2/dof and p-values by up to ~6e-7 (the 30-minute
session of seed 2, on the Nehalem kernel), and a calibration's temperature coefficients by
~1e-8, a magnetometer covariance by ~1e-6. So each check is repeated with each of
``--floor-kernels`` (x86-64 kernels every such CPU with AVX runs), and a number passes when it
is within ``rtol``, or within ``FLOOR_FACTOR`` times its largest spread from this machine's
kernel (the map's stage rerun alone on each kernel; the calibration run afresh on each).

``--check`` then runs the whole pipeline afresh and compares ``calibration.json`` with the
saved run's, each field relative to its largest value, by the same rule; a field also passes
within ``STAT_FRACTION`` of its own statistical spread: a calibration parameter's standard
error, a joint fit block's chi2's sqrt(2 dof) (the fit's optimum is only defined to
sqrt(rounding x chi2), ~6e-5 standard errors; a kernel may follow this machine's rounding path
by chance and leave a field unmoved).
Exit status 1 names the worst number when they differ. Run ``--save`` with the code before a
change (e.g. main's virtual environment) and ``--check`` after it: issue 13's "results
identical within 1e-9 relative on a fixed session".
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

FLOOR_FACTOR = 10.0  # a number within this many times its spread over BLAS kernels is the same result
STAT_FRACTION = 1e-5  # ... or (a calibration field) within this fraction of its statistical spread
SIGMAS = {"M": "sigma_M", "b0": "sigma_b0", "k": "sigma_k"}
# x86-64 only (elsewhere none: every number is then judged at rtol alone)
FLOOR_KERNELS = "Prescott,Nehalem,Sandybridge" if platform.machine().lower() in ("x86_64", "amd64") else ""


def _run(folder: Path, session: Path, out: Path, *extra: str, env: dict | None = None) -> None:
    # run from the scratch folder: ``-m`` then finds the imupipe this interpreter has installed,
    # not a checkout that happens to be the working directory
    subprocess.run([sys.executable, "-m", "imupipe.cli", "run", str(session), "--out", str(out), "--quiet", *extra],
                   check=True, stdout=subprocess.DEVNULL, cwd=folder, env=env)


def fresh_calibration(folder: Path, session: Path, name: str, kernel: str | None = None) -> dict:
    """``calibration.json`` of a run with nothing cached (``kernel``: OpenBLAS's core type)."""
    env = None if kernel is None else {**os.environ, "OPENBLAS_CORETYPE": kernel}
    out = folder / name
    _run(folder, session, out, env=env)
    return json.loads((out / session.stem / "calibration.json").read_text())


def numeric_fields(doc, path: str = "") -> dict[str, np.ndarray]:
    """Every number of a JSON document, by field (a list of numbers is one field); strings as such."""
    if isinstance(doc, dict):
        return {k: v for key in doc for k, v in numeric_fields(doc[key], f"{path}/{key}").items()}
    if isinstance(doc, list) and doc and all(isinstance(x, (int, float, list)) for x in doc):
        try:
            return {path: np.array(doc, float)}
        except ValueError:  # ragged
            pass
    if isinstance(doc, list):
        return {k: v for i, x in enumerate(doc) for k, v in numeric_fields(x, f"{path}[{i}]").items()}
    if isinstance(doc, (int, float)) and not isinstance(doc, bool):
        return {path: np.array([doc], float)}
    return {path: doc}


def field_difference(a, b) -> float:
    """Largest difference relative to the field's largest value (inf: not comparable)."""
    if not isinstance(a, np.ndarray) or not isinstance(b, np.ndarray):
        return 0.0 if a == b else math.inf
    if a.shape != b.shape or not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return math.inf
    ok = np.isfinite(a)
    d = float(np.abs(a[ok] - b[ok]).max()) if ok.any() else 0.0
    scale = float(np.abs(a[ok]).max()) if ok.any() else 0.0
    return d / scale if scale else d


def statistical_change(name: str, ref: dict, new: dict) -> float:
    """The change of a calibration parameter (M, b0, k) in its standard errors, or of a joint fit
    block's chi2 (chi2/dof, RMS) in chi2's spread sqrt(2 dof); inf for other fields."""
    parts = name.strip("/").split("/")
    a, b = ref.get(name), new.get(name)
    if not isinstance(a, np.ndarray) or not isinstance(b, np.ndarray) or a.shape != b.shape:
        return math.inf
    if len(parts) == 2 and parts[1] in SIGMAS:
        sd = new.get(f"/{parts[0]}/{SIGMAS[parts[1]]}")
        if isinstance(sd, np.ndarray) and sd.shape == a.shape and (sd > 0).all():
            return float(np.nanmax(np.abs(a - b) / sd))
        return math.inf
    if parts[1:3] == ["joint", "blocks"] and len(parts) == 5:
        block, what = parts[3], parts[4]
    elif parts[1:3] == ["joint", "rms_whitened"] and len(parts) == 4:
        block, what = parts[3], "rms"
    else:
        return math.inf
    stats = {k: new.get(f"/{parts[0]}/joint/blocks/{block}/{k}") for k in ("dof", "rows", "rms")}
    if any(not isinstance(v, np.ndarray) for v in stats.values()) or stats["dof"][0] <= 0:
        return math.inf
    d = float(np.abs(a - b).max())
    dchi2 = {"chi2": d, "chi2_per_dof": d * stats["dof"][0],
             "rms": 2 * stats["rms"][0] * d * stats["rows"][0]}.get(what)
    return math.inf if dchi2 is None else dchi2 / math.sqrt(2 * stats["dof"][0])


def allowance(spreads: Iterable[float], rtol: float) -> float:
    """max(rtol, FLOOR_FACTOR x the largest finite spread): what rounding alone moves a number by
    (``spreads``: the new code's differences between this machine's BLAS kernel and others; a
    kernel that changed the number's shape, inf, sets no floor)."""
    return max(rtol, FLOOR_FACTOR * max((d for d in spreads if math.isfinite(d)), default=0.0))


def compare_calibrations(ref: dict, new: dict, other_kernels: list[dict],
                         rtol: float) -> list[tuple[float, float, str, str]]:
    """Per field: (difference, allowed, name, by what), allowed = ``allowance`` of the field's
    spreads between ``new`` and ``other_kernels`` (the same code's runs on other BLAS kernels); a
    field within ``STAT_FRACTION`` of its statistical spread is allowed its difference. The
    session's path is not compared."""
    fr, fn = (numeric_fields({k: v for k, v in d.items() if k != "session"}) for d in (ref, new))
    fk = [numeric_fields(d) for d in other_kernels]
    out = []
    for name in sorted(set(fr) | set(fn)):
        if name not in fr or name not in fn:
            out.append((math.inf, rtol, f"{name} only in one", "rtol"))
            continue
        d = field_difference(fr[name], fn[name])
        allowed = allowance((field_difference(fn[name], f[name]) for f in fk if name in f), rtol)
        how = "kernels" if allowed > rtol else "rtol"
        if d > allowed and statistical_change(name, fr, fn) <= STAT_FRACTION:
            allowed, how = d, "statistical"
        out.append((d, allowed, name, how))
    return out


def _gravity(run: Path) -> float:
    cal = json.loads((run / "calibration.json").read_text())
    for triad in ("gyro", "accel"):
        g = cal.get(triad, {}).get("joint", {}).get("gravity_m_s2")
        if g:
            return float(g)
    return 9.80665


def produce(folder: Path, protocol: str, seed: int, fresh: bool,
            kernel: str | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """The map stage's outputs on the session in ``folder`` (the document without the session's
    path): simulated and run when ``fresh``; else the map stage is rerun alone (its local
    gravity set to the value it reads from the calibration anyway: a new cache key, the same
    numbers) on the stages before it as the cache holds them, so only the map stage's own code
    is compared; ``kernel``: OpenBLAS's core type for that rerun."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    session, out = folder / f"{protocol}.mcap", folder / "out"
    if fresh:
        from imupipe.sim.api import simulate

        simulate(protocol, {}, seed, session, quiet=True)
        _run(folder, session, out)
    run = out / session.stem
    if not fresh:  # the saved outputs are the first run's; this key is new to the cache
        env = None if kernel is None else {**os.environ, "OPENBLAS_CORETYPE": kernel}
        _run(folder, session, out, "--set", f"map.g_m_s2={_gravity(run)!r}", env=env)
    table = pq.read_table(run / "residuals.parquet")
    arrays = {}
    for name in table.column_names:
        col = table.column(name).combine_chunks()
        if pa.types.is_fixed_size_list(col.type):
            arrays[name] = col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), -1)
        else:
            arrays[name] = col.to_numpy(zero_copy_only=False)
    doc = json.loads((run / "residual_map.json").read_text())
    doc.pop("session", None)  # the scratch folder's path
    return arrays, doc


def compare_arrays(ref: dict[str, np.ndarray], new: dict[str, np.ndarray]) -> list[tuple[float, str]]:
    out = []
    for name in sorted(set(ref) | set(new)):
        if name not in ref or name not in new:
            out.append((math.inf, f"column {name} only in one"))
            continue
        a, b = ref[name], new[name]
        if a.shape != b.shape:
            out.append((math.inf, f"column {name}: shape {a.shape} vs {b.shape}"))
        elif a.dtype.kind in "fc":
            if not np.array_equal(np.isfinite(a), np.isfinite(b)):
                out.append((math.inf, f"column {name}: NaNs differ"))
            else:
                out.append((field_difference(a, b), f"column {name}"))
        elif not np.array_equal(a, b):
            out.append((math.inf, f"column {name}: values differ"))
    return out


def compare_json(a, b, path: str = "") -> list[tuple[float, str]]:
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [(math.inf, f"{path}: keys {sorted(set(a) ^ set(b))}")]
        return [x for k in a for x in compare_json(a[k], b[k], f"{path}/{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [(math.inf, f"{path}: {len(a)} vs {len(b)} items")]
        return [x for i, (u, v) in enumerate(zip(a, b, strict=True)) for x in compare_json(u, v, f"{path}[{i}]")]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        if a == b or (math.isnan(a) and math.isnan(b)):
            return [(0.0, path)]
        if path.endswith("p_value") and a > 0 and b > 0:
            a, b = -math.log10(a), -math.log10(b)
        return [(abs(a - b) / max(abs(a), abs(b)), path)]
    return [(0.0 if a == b else math.inf, path)]


def compare_maps(ref: tuple[dict, dict], new: tuple[dict, dict]) -> list[tuple[float, str]]:
    """(difference, name) of every per-sample column and every number of the map document."""
    return compare_arrays(ref[0], new[0]) + compare_json(ref[1], new[1], "residual_map.json")


def judge_map(diffs: list[tuple[float, str]], spreads: list[list[tuple[float, str]]],
              rtol: float) -> list[tuple[float, float, str]]:
    """Per number: (difference, allowed, name), allowed = ``allowance`` of its spreads in
    ``spreads`` (the new code's differences, by ``compare_maps``, between this machine's kernel
    and each other kernel)."""
    by_name: dict[str, list[float]] = {}
    for kernel in spreads:
        for d, name in kernel:
            by_name.setdefault(name, []).append(d)
    return [(d, allowance(by_name.get(name, ()), rtol), name) for d, name in diffs]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--save", type=Path, help="store the numbers as SAVE.npz and SAVE.json")
    what.add_argument("--check", type=Path, help="compare with CHECK.npz and CHECK.json")
    ap.add_argument("--protocol", default="standard")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rtol", type=float, default=1e-9)
    ap.add_argument("--floor-kernels", default=FLOOR_KERNELS,
                    help="OpenBLAS core types whose rounding sets each number's floor ('' for none)")
    args = ap.parse_args()
    import imupipe  # noqa: F401  (which one: printed below)

    if args.save:
        folder = args.save.with_suffix(".d")
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        arrays, doc = produce(folder, args.protocol, args.seed, fresh=True)
    else:  # a copy of the saved run: its cache holds the stages before the map, as saved
        with tempfile.TemporaryDirectory(prefix="residual-identity-") as tmp:
            folder = Path(tmp) / "run"
            shutil.copytree(args.check.with_suffix(".d"), folder)
            arrays, doc = produce(folder, args.protocol, args.seed, fresh=False)
            kernels = [k for k in args.floor_kernels.split(",") if k]
            map_spreads = []
            for k in kernels:  # the map stage alone on each kernel, each on its own copy of the cache
                scratch = Path(tmp) / f"run-{k}"
                shutil.copytree(args.check.with_suffix(".d"), scratch)
                map_spreads.append(compare_maps((arrays, doc), produce(scratch, args.protocol, args.seed, False, k)))
                shutil.rmtree(scratch)
            session = folder / f"{args.protocol}.mcap"
            saved = json.loads((folder / "out" / session.stem / "calibration.json").read_text())
            fresh = fresh_calibration(folder, session, "fresh")
            other = [fresh_calibration(folder, session, f"kernel-{k}", k) for k in kernels]
    if args.save:
        np.savez(args.save.with_suffix(".npz"), **{k: v for k, v in arrays.items() if v.dtype != object},
                 **{f"str:{k}": v.astype(str) for k, v in arrays.items() if v.dtype == object})
        args.save.with_suffix(".json").write_text(json.dumps(doc))
        print(f"imupipe from {Path(sys.modules['imupipe'].__file__).parent}")
        print(f"saved {len(arrays)} columns of {len(next(iter(arrays.values())))} rows and the map document "
              f"to {args.save}.npz/.json (the run: {folder})")
        return
    print(f"imupipe from {Path(sys.modules['imupipe'].__file__).parent}")
    with np.load(args.check.with_suffix(".npz")) as z:
        ref = {k.removeprefix("str:"): z[k] for k in z.files}
    arrays = {k: (v.astype(str) if v.dtype == object else v) for k, v in arrays.items()}
    ref_doc = json.loads(args.check.with_suffix(".json").read_text())
    ref_doc.pop("session", None)  # the saving run's scratch folder
    judged = judge_map(compare_maps((ref, ref_doc), (arrays, doc)), map_spreads, args.rtol)
    failed = False
    for what, unit, part in (("per-sample columns", "columns", [j for j in judged if j[2].startswith("column")]),
                             ("map document", "numbers", [j for j in judged if not j[2].startswith("column")])):
        d, allowed, name = max(part, key=lambda f: (f[0] / max(f[1], 1e-300), f[0]))
        beyond = [j for j in part if j[0] > args.rtol]
        print(f"{what}: {len(part)} {unit}, worst {max(part)[0]:.2e} ({max(part)[2]}); {len(beyond)} beyond "
              f"{args.rtol:g}, {sum(j[0] <= j[1] for j in beyond)} of them within {FLOOR_FACTOR:g}x their spread on "
              f"OpenBLAS's {', '.join(kernels) or 'no other'} kernels; worst against its allowance {d:.2e} of "
              f"{allowed:.2e} ({name})")
        if d > allowed:
            print(f"DIFFERENT: {name} differs by {d:.3g} relative (allowed {allowed:.3g})")
            failed = True
    fields = compare_calibrations(saved, fresh, other, args.rtol)
    d, allowed, name, _ = max(fields, key=lambda f: (f[0] / f[1], f[0]))
    beyond = [f for f in fields if f[0] > args.rtol]
    print(f"calibration.json, run afresh: {len(fields)} fields, worst {max(fields)[0]:.2e} ({max(fields)[2]}); "
          f"{len(beyond)} beyond {args.rtol:g}: {sum(f[3] == 'kernels' and f[0] <= f[1] for f in beyond)} within "
          f"{FLOOR_FACTOR:g}x their spread on OpenBLAS's {', '.join(kernels) or 'no other'} kernels, "
          f"{sum(f[3] == 'statistical' for f in beyond)} within {STAT_FRACTION:g} of their statistical spread; "
          f"worst against its allowance {d:.2e} of {allowed:.2e} ({name})")
    if d > allowed:
        print(f"DIFFERENT: calibration.json{name} differs by {d:.3g} relative (allowed {allowed:.3g})")
        failed = True
    if failed:
        sys.exit(1)
    print(f"identical: every number within {args.rtol:g} relative or its rounding floor")


if __name__ == "__main__":
    main()

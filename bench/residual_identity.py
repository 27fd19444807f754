"""The residual map's numbers on a fixed session, saved by one version of imupipe and checked by another.

    python bench/residual_identity.py --save REF [--seed 0] [--protocol standard]
    python bench/residual_identity.py --check REF [--rtol 1e-9]

``--save`` simulates the session (``imupipe simulate``'s protocol and seed; the standard
protocol is the 30-minute session of ``bench/residual_cost.py``) into ``REF.d``, runs the
default pipeline on it; ``--check`` reruns the map stage
alone on a copy of ``REF.d``, whose cache holds the stages before it as they were saved (so
an upstream change, amplified by the fits' stopping rules, does not mask the map's own). Both
read what the map stage wrote: ``residuals.parquet`` (every sample's prediction, residual
and whitened residual, gravity, |omega|, |alpha|, ...) and ``residual_map.json`` (every
cell's and block's chi2, dof, p-value, events, change points). ``--save`` stores them as
``REF.npz`` and ``REF.json``; ``--check`` recomputes them with the imupipe this Python
imports and compares every number: equal within ``rtol`` relative (of the value, or of its
column's largest for per-sample columns; p-values on ``-log10 p``), strings and shapes equal.
Exit status 1 names the worst field when they differ. Run ``--save`` with the code before a
change (e.g. main's virtual environment) and ``--check`` after it: issue 13's "results
identical within 1e-9 relative on a fixed session".
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def _run(folder: Path, session: Path, out: Path, *extra: str) -> None:
    # run from the scratch folder: ``-m`` then finds the imupipe this interpreter has installed,
    # not a checkout that happens to be the working directory
    subprocess.run([sys.executable, "-m", "imupipe.cli", "run", str(session), "--out", str(out), "--quiet", *extra],
                   check=True, stdout=subprocess.DEVNULL, cwd=folder)


def _gravity(run: Path) -> float:
    cal = json.loads((run / "calibration.json").read_text())
    for triad in ("gyro", "accel"):
        g = cal.get(triad, {}).get("joint", {}).get("gravity_m_s2")
        if g:
            return float(g)
    return 9.80665


def produce(folder: Path, protocol: str, seed: int, fresh: bool) -> tuple[dict[str, np.ndarray], dict]:
    """The map stage's outputs on the session in ``folder``: simulated and run when ``fresh``;
    else the map stage is rerun alone (its local gravity set to the value it reads from the
    calibration anyway: a new cache key, the same numbers) on the stages before it as the
    cache holds them, so only the map stage's own code is compared."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    session, out = folder / f"{protocol}.mcap", folder / "out"
    if fresh:
        from imupipe.sim.api import simulate

        simulate(protocol, {}, seed, session, quiet=True)
        _run(folder, session, out)
    run = out / session.stem
    if not fresh:  # the saved outputs are the first run's; this key is new to the cache
        _run(folder, session, out, "--set", f"map.g_m_s2={_gravity(run)!r}")
    table = pq.read_table(run / "residuals.parquet")
    arrays = {}
    for name in table.column_names:
        col = table.column(name).combine_chunks()
        if pa.types.is_fixed_size_list(col.type):
            arrays[name] = col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), -1)
        else:
            arrays[name] = col.to_numpy(zero_copy_only=False)
    return arrays, json.loads((run / "residual_map.json").read_text())


def compare_arrays(ref: dict[str, np.ndarray], new: dict[str, np.ndarray], rtol: float) -> list[tuple[float, str]]:
    out = []
    for name in sorted(set(ref) | set(new)):
        if name not in ref or name not in new:
            out.append((math.inf, f"column {name} only in one"))
            continue
        a, b = ref[name], new[name]
        if a.shape != b.shape:
            out.append((math.inf, f"column {name}: shape {a.shape} vs {b.shape}"))
        elif a.dtype.kind in "fc":
            fa, fb = np.isfinite(a), np.isfinite(b)
            if not np.array_equal(fa, fb):
                out.append((math.inf, f"column {name}: NaNs differ"))
                continue
            scale = float(np.abs(a[fa]).max()) if fa.any() else 0.0
            d = float(np.abs(a[fa] - b[fb]).max()) / scale if scale else 0.0
            out.append((d, f"column {name}"))
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--save", type=Path, help="store the numbers as SAVE.npz and SAVE.json")
    what.add_argument("--check", type=Path, help="compare with CHECK.npz and CHECK.json")
    ap.add_argument("--protocol", default="standard")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rtol", type=float, default=1e-9)
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
    diffs = compare_arrays(ref, arrays, args.rtol)
    ref_doc = json.loads(args.check.with_suffix(".json").read_text())
    ref_doc.pop("session", None), doc.pop("session", None)  # the scratch folder's path
    diffs += compare_json(ref_doc, doc, "residual_map.json")
    worst = max(diffs)
    columns = [d for d in diffs if d[1].startswith("column")]
    print(f"per-sample columns: worst relative difference {max(columns)[0]:.2e} ({max(columns)[1]})")
    print(f"map document: {len(diffs) - len(columns)} numbers, worst {max(d for d in diffs if d not in columns)[0]:.2e} "
          f"({max(d for d in diffs if d not in columns)[1]})")
    if worst[0] > args.rtol:
        print(f"DIFFERENT: {worst[1]} differs by {worst[0]:.3g} relative (tolerance {args.rtol:g})")
        sys.exit(1)
    print(f"identical within {args.rtol:g} relative")


if __name__ == "__main__":
    main()

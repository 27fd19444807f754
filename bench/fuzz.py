"""The fault campaign of issue 12: mutated sessions through ``imupipe run``/``ingest``.

    python bench/fuzz.py [--cases 400] [--seed 0] [--base FILE ...] [--timeout 180] [--kills 15]

Each case is a mutation from ``tests/fuzz/mutate.py`` of a base session (by
default two small simulated sessions, CSV and MCAP, made once) laid out in its
own sandbox with decoy files beside ``--out``. Every case runs the real command
line (``imupipe.cli.main``) in a forked child with a time limit. Printed at the
end, one row per mutation and a total; target 0 in every column but ``cases``:

    cases            how many ran
    tracebacks       a Python traceback or an "internal error" line on stderr, a crash or a hang
    bad_exit         bad input (or a hostile name on good data) whose exit status was not 2
                     (not 0 for good input; 0 or 2 for a mutation that may stay usable)
    multi_line       a failure whose stderr did not end in one error line, or had anything but
                     imupipe's own one-line warnings before it (numpy noise, a second line)
    outside_out      a file outside --out created, changed or deleted
    half_written     a .part left, an unreadable .json/.arrow, or a calibration.json after a failure
    silent_wrong     exit 0 with an accel or gyro M or b0 more than 10 times its own 1-sigma from
                     the clean base's calibration, and no warning that the clean run did not give
                     (no new imupipe warning line, no verdict check worse than the clean run's)

With ``--kills N``, ``imupipe batch`` is then killed (SIGKILL) N times at random points
on one output folder: every complete cache entry must verify after each kill, and the
final rerun must equal a clean run byte for byte with no ``.part`` left.

Most cases use the default pipeline without its reports (faster); every 10th
uses the full default pipeline, reports included.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "fuzz"))

import numpy as np
from mutate import ANY_FORMAT, MUTATIONS, half_written, make_case, snapshot

COLUMNS = ("cases", "tracebacks", "bad_exit", "multi_line", "outside_out", "half_written",
           "silent_wrong")
SILENT_SIGMAS = 10.0  # a calibration this many of its own sigmas from the clean one is another answer
ORDER = {"pass": 0, "warn": 1, "fail": 2}


def base_sessions(folder: Path) -> list[Path]:
    """Two small simulated sessions (25 Hz sphere rig, ~2 min), CSV and MCAP."""
    import subprocess

    params = {"warmup_s": 20, "n_positions": 24, "n_turns": 14, "rest_s": 3,
              "reference_rest_s": 3}
    out = []
    for suffix in (".csv", ".mcap"):
        path = folder / f"base{suffix}"
        if not path.is_file():  # in a child: polars' thread pool must not exist before a fork
            subprocess.run([sys.executable, "-m", "imupipe.cli", "simulate", "sphere_rig",
                            "--seed", "1", "--out", str(path), "--quiet", "--imu", "rate_hz=25",
                            *[a for k, v in params.items() for a in ("--param", f"{k}={v}")]],
                           check=True, stdout=subprocess.DEVNULL)
        out.append(path)
    return out


def light_pipeline(folder: Path) -> Path:
    """The default pipeline without its reports and residual map (the campaign's time goes
    to many cases, not to figures)."""
    from imupipe.pipeline.config import default_pipeline_path

    text = default_pipeline_path().read_text()
    head, _, rest = text.partition("[stages.map]")
    export = rest[rest.index("[export]"):]
    export = "\n".join(line for line in export.splitlines() if not line.startswith("reports"))
    path = folder / "light.toml"
    path.write_text(head + export + "\n")
    return path


def preload() -> None:
    """Import what every case needs once, in the parent (no library thread pool is started:
    the children are forked from it)."""
    import imupipe.cli
    import imupipe.pipeline.api  # noqa: F401
    from imupipe.plugins import make_registry

    make_registry()


def run_cli(argv: list[str], cwd: Path, timeout: float) -> tuple[int | str, str]:
    """``imupipe.cli.main(argv)`` in a forked child; (exit status or "crash"/"hang", stderr)."""
    err_path = cwd.parent / f"{cwd.name}.stderr"
    pid = os.fork()
    if pid == 0:  # child
        code = 1
        try:
            fd = os.open(err_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            os.dup2(fd, 2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            sys.stderr = io.TextIOWrapper(os.fdopen(2, "wb", closefd=False), write_through=True)
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115
            os.chdir(cwd)
            import logging

            logging.getLogger().handlers.clear()
            from imupipe import cli

            code = cli.main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
        except BaseException:  # noqa: BLE001 - what escapes main is the finding
            import traceback

            traceback.print_exc()
            code = 1
        finally:
            sys.stderr.flush()
            os._exit(code)
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return "hang", err_path.read_text(errors="replace") if err_path.exists() else ""
        time.sleep(0.05)
    err = err_path.read_text(errors="replace")
    err_path.unlink()
    if os.WIFSIGNALED(status):
        return "crash", err
    return os.WEXITSTATUS(status), err


def warning_kinds(err: str) -> set[str]:
    """imupipe's warning lines with file names and numbers blanked (comparable across sessions)."""
    out = set()
    for line in err.splitlines():
        if line.startswith("imupipe: warning: "):
            line = re.sub(r"\S*\.(?:csv|mcap|toml|arrow)\S*", "<file>", line)
            out.add(re.sub(r"[-+]?\d[\d.]*(?:e[-+]?\d+)?", "#", line))
    return out


def verdict_levels(doc: dict) -> dict[str, int]:
    """Worst status per verdict check name (a check made twice keeps its worst)."""
    levels: dict[str, int] = {}
    for c in (doc.get("verdict") or {}).get("checks", []):
        levels[c["check"]] = max(levels.get(c["check"], 0), ORDER.get(c["status"], 2))
    return levels


def clean_reference(base: Path, pipeline: Path | None, work: Path, timeout: float) -> dict | None:
    """The clean base's calibration through ``pipeline`` (None: the default): the answer the
    mutations are compared with, and its warnings (those a mutated run shares are not news)."""
    sandbox = work / f"ref-{base.name}-{pipeline.stem if pipeline else 'default'}"
    sandbox.mkdir(parents=True, exist_ok=True)
    argv = ["run", str(base.resolve()), "--out", "out", "--quiet"]
    code, err = run_cli(argv + (["--pipeline", str(pipeline.resolve())] if pipeline else []),
                        sandbox, timeout)
    found = sorted((sandbox / "out").rglob("calibration.json"))
    if code != 0 or not found:
        print(f"clean run of {base} failed ({code}): {err.strip()[-300:]}")
        return None
    return {"doc": json.loads(found[0].read_text()), "warnings": warning_kinds(err)}


def sigmas_away(doc: dict, ref: dict) -> float:
    """Largest |difference| of accel and gyro M and b0 from ``ref`` in units of ``doc``'s own
    1-sigma (the reference's where ``doc`` gives none)."""
    worst = 0.0
    for sensor in ("accel", "gyro"):
        a, b = doc.get(sensor), ref.get(sensor)
        if not a or not b:
            continue
        for key, skey in (("M", "sigma_M"), ("b0", "sigma_b0")):
            d = np.abs(np.asarray(a[key], float) - np.asarray(b[key], float))
            sigma = np.asarray(a.get(skey) or b.get(skey) or np.full(d.shape, np.nan), float)
            bad = ~(np.isfinite(sigma) & (sigma > 0))
            if bad.any() and b.get(skey) is not None:
                sigma = np.where(bad, np.asarray(b[skey], float), sigma)
            z = d / sigma
            if not np.isfinite(d).all():
                return float("inf")
            z = z[np.isfinite(z)]
            worst = max(worst, float(z.max()) if z.size else 0.0)
    return worst


def silent_wrong(case, code, err, out: Path, ref: dict | None) -> int:
    """1 when the run exited 0 with another answer than the clean base's and said nothing new."""
    if ref is None or code != 0 or case.command != "run" or case.pipeline:
        return 0
    found = sorted(out.rglob("calibration.json"))
    if not found:
        return 0
    try:
        doc = json.loads(found[0].read_text())
    except ValueError:
        return 0  # half_written says it
    z = sigmas_away(doc, ref["doc"])
    case.notes["sigmas"] = round(z, 1)
    if z <= SILENT_SIGMAS:
        return 0
    clean = verdict_levels(ref["doc"])
    news = {k for k, v in verdict_levels(doc).items() if v > clean.get(k, 0)}
    news |= warning_kinds(err) - ref["warnings"]
    case.notes["news"] = sorted(news)[:3]
    return int(not news)


def judge(case, code, err, before, after, out: Path, ref: dict | None = None) -> dict[str, int]:
    row = dict.fromkeys(COLUMNS, 0)
    row["cases"] = 1
    if code in ("hang", "crash") or "Traceback" in err or "internal error" in err:
        row["tracebacks"] = 1
    if case.expect == "bad":
        ok = code == 2
    elif case.expect == "good":
        ok = code == 0
    else:
        ok = code in (0, 2)
    row["bad_exit"] = int(not ok)
    if code == 2:  # one error line last; before it only imupipe's own warning lines, no numpy noise
        lines = [line for line in err.splitlines() if line.strip()]
        row["multi_line"] = int(
            not lines or " error: " not in lines[-1]
            or any(not ln.startswith("imupipe: warning: ") or "encountered in" in ln
                   for ln in lines[:-1]))
    row["outside_out"] = int(before != after)
    bad = half_written(out)
    if code != 0:
        bad += [str(p) for p in out.rglob("calibration.json")]
    row["half_written"] = int(bool(bad))
    case.notes["half"] = bad[:3]
    row["silent_wrong"] = silent_wrong(case, code, err, out, ref)
    if before != after:
        changed = sorted(set(before.items()) ^ set(after.items()))
        case.notes["outside"] = changed[:5]
    return row


def kill_campaign(base: Path, light: Path, work: Path, kills: int, rng) -> dict[str, int]:
    """SIGKILL ``imupipe batch`` at random points; after each kill every complete cache entry
    must verify; the final rerun must equal a clean run byte for byte and leave no .part."""
    import json
    import subprocess

    from imupipe.pipeline.cache import Cache

    def batch(out: Path) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-m", "imupipe.cli", "batch", str(base), "--out", str(out),
             "--pipeline", str(light), "--jobs", "1", "--quiet"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)

    ref_out = work / "kill-ref"
    t0 = time.monotonic()
    batch(ref_out).wait()
    clean_s = time.monotonic() - t0
    ref = (ref_out / base.stem / "calibration.json").read_bytes()
    out = work / "kill-out"
    row = {"kills": 0, "unverified_entries": 0, "half_written": 0, "rerun_differs": 0}
    for _ in range(kills):
        proc = batch(out)
        time.sleep(float(rng.uniform(0.5, clean_s)))
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        row["kills"] += 1
        cache = Cache(out / ".cache")
        for index in (out / ".cache").glob("*/*/outputs.json"):
            if cache.entry(index.parent.name) is None:
                row["unverified_entries"] += 1
        for p in out.rglob("*.json"):
            try:
                json.loads(p.read_text())
            except ValueError:
                row["half_written"] += 1
    batch(out).wait()
    if (out / base.stem / "calibration.json").read_bytes() != ref:
        row["rerun_differs"] = 1
    row["half_written"] += len([p for p in out.rglob("*") if p.name.endswith(".part")
                                or p.name.startswith(".part-")])
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--base", type=Path, action="append", default=[])
    ap.add_argument("--timeout", type=float, default=180.0)
    ap.add_argument("--work", type=Path, default=None, help="keep sandboxes here (default: temp)")
    ap.add_argument("--kinds", default="", help="comma-separated mutations (default: all)")
    ap.add_argument("--kills", type=int, default=0,
                    help="also SIGKILL `imupipe batch` this many times at random points")
    args = ap.parse_args()

    work = args.work or Path(tempfile.mkdtemp(prefix="imupipe-fuzz-"))
    work.mkdir(parents=True, exist_ok=True)
    bases = args.base or base_sessions(work)
    light = light_pipeline(work)
    preload()
    refs = {(b, full): clean_reference(b, None if full else light, work, args.timeout)
            for b in bases for full in (False, True)}
    for (b, full), ref in refs.items():  # the measure itself: 0 for the clean answer, large for another
        if ref is not None:
            other = json.loads(json.dumps(ref["doc"]))
            other["accel"]["b0"][0] += 0.05
            assert sigmas_away(ref["doc"], ref["doc"]) == 0 and sigmas_away(other, ref["doc"]) > 10
    kinds = [k for k in args.kinds.split(",") if k] or sorted(MUTATIONS)
    rng = np.random.default_rng(args.seed)
    totals: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    findings = []
    compared: list[tuple[float, str]] = []  # (sigmas from the clean answer, mutation) of exit-0 runs
    t0 = time.monotonic()
    for i in range(args.cases):
        kind = kinds[i % len(kinds)]
        csv = [b for b in bases if b.suffix.lower() == ".csv"]
        base = (bases[(i // len(kinds)) % len(bases)] if kind in ANY_FORMAT or not csv
                else csv[(i // len(kinds)) % len(csv)])
        sandbox = work / f"case{i:04d}"
        case = make_case(kind, rng, sandbox, base)
        full = i % 10 == 9
        argv = [case.command, f"in/{case.session}", "--out", "out", "--quiet"]
        if case.command == "run":
            pipeline = f"in/{case.pipeline}" if case.pipeline else (None if full else str(light))
            argv += ["--pipeline", pipeline] if pipeline else []
        before = snapshot(sandbox)
        code, err = run_cli(argv, sandbox, args.timeout)
        after = snapshot(sandbox)
        row = judge(case, code, err, before, after, sandbox / "out", refs.get((base, full)))
        if "sigmas" in case.notes:
            compared.append((case.notes["sigmas"], case.name))
        totals[case.name].update(row)
        totals["TOTAL"].update(row)
        if any(row[c] for c in COLUMNS[1:]):
            findings.append((i, case, code, err.strip().splitlines()[-3:], row))
        print(f"case {i:4d} {case.name:22s} {base.suffix:6s} exit {code!s:5s} "
              f"{'!' if any(row[c] for c in COLUMNS[1:]) else ' '} {time.monotonic() - t0:7.0f} s"
              + (f"  {case.notes['sigmas']:g} sigmas from clean" if "sigmas" in case.notes else ""),
              flush=True)
        if args.work is None:
            shutil.rmtree(sandbox, ignore_errors=True)
    print()
    print(f"{'mutation':22s} " + " ".join(f"{c:>12s}" for c in COLUMNS))
    print(f"(silent_wrong: exit 0, accel/gyro more than {SILENT_SIGMAS:g} own sigmas from the clean "
          "base's calibration, no new warning)")
    for name in sorted(k for k in totals if k != "TOTAL") + ["TOTAL"]:
        print(f"{name:22s} " + " ".join(f"{totals[name][c]:12d}" for c in COLUMNS))
    top, top_kind = max(compared, default=(0.0, "-"))
    print(f"\n{len(compared)} runs exited 0 with a calibration compared with the clean one; largest "
          f"difference {top:g} own sigmas ({top_kind})")
    print(f"{len(findings)} findings in {time.monotonic() - t0:.0f} s")
    for i, case, code, tail, row in findings[:40]:
        cols = ",".join(c for c in COLUMNS[1:] if row[c])
        print(f"  case {i} {case.name} ({case.expect}, {case.command} {case.session}) exit {code} "
              f"[{cols}] {case.notes}: {' | '.join(t[:300] for t in tail)}")
    if args.kills:
        csv = [b for b in bases if b.suffix.lower() == ".csv"] or bases
        row = kill_campaign(csv[0], light, work, args.kills, rng)
        print("\nSIGKILL of batch: " + ", ".join(f"{k} {v}" for k, v in row.items()))
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Command line (``spec/contracts.md``): thin; parses, delegates, shows progress.

Exit status: 0 success, 2 bad usage or bad input (one line naming the file and
what is wrong), 1 internal failure, 3 with ``--strict`` when a verdict is warn or fail.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import re
import sys
from pathlib import Path

from . import __version__
from .errors import ImupipeError

log = logging.getLogger("imupipe")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="imupipe", description="Calibrate MEMS IMUs from recorded sessions.")
    p.add_argument("--version", action="version", version=f"imupipe {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--quiet", action="store_true", help="no progress display")

    def blas(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--blas-threads", type=int, default=None, metavar="N",
                        help="BLAS threads per process/worker (default $IMUPIPE_BLAS_THREADS, else 1)")

    def strict(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--strict", action="store_true",
                        help="exit status 3 when a calibration's verdict is warn or fail")

    def exports(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--export", action="append", default=[], metavar="FORMAT[,...]",
                        help="also write the calibration for other software, in DIR/<session>/"
                             "export/: kalibr, imu_tk, px4, ardupilot, imu_calib")

    def pipeline_options(sp: argparse.ArgumentParser) -> None:
        """--pipeline, --set, --device: run, batch, status (and diagnose) take the same ones."""
        sp.add_argument("--pipeline", type=Path, default=None, metavar="FILE_OR_NAME",
                        help="pipeline TOML, or the name of a shipped one (imupipe pipelines); "
                             "default: the built-in one")
        sp.add_argument("--set", action="append", default=[], dest="overrides",
                        metavar="STAGE.PARAM=VALUE",
                        help="override a pipeline parameter, e.g. --set accel.g_m_s2=9.81 "
                             "(validated like the pipeline file)")
        sp.add_argument("--device", default=None, metavar="NAME",
                        help="which IMU of a multi-IMU recording (the pipeline's [input] device)")

    sp = sub.add_parser("ingest", help="read a session into canonical Arrow tables")
    sp.add_argument("session", type=Path)
    sp.add_argument("--out", type=Path, default=None, help="output directory (default: ./<session-stem>.tables)")
    common(sp)

    sp = sub.add_parser("run", help="calibrate one or more sessions")
    sp.add_argument("sessions", type=Path, nargs="+", metavar="SESSION")
    pipeline_options(sp)
    sp.add_argument("--out", type=Path, default=Path("imupipe-out"))
    exports(sp)
    blas(sp)
    strict(sp)
    common(sp)

    sp = sub.add_parser("diagnose", help="say which physics the calibrated model leaves out, fit it, "
                                         "check it on held-out data; several sessions of one unit are "
                                         "also diagnosed pooled (DIR/pooled/)")
    sp.add_argument("sessions", type=Path, nargs="+", metavar="SESSION")
    pipeline_options(sp)  # a pipeline with a map_residuals stage (default: the built-in one)
    sp.add_argument("--out", type=Path, default=Path("imupipe-out"))
    strict(sp)
    common(sp)

    sp = sub.add_parser("batch", help="calibrate every session under directories or globs")
    sp.add_argument("inputs", nargs="+", metavar="GLOB_OR_DIR")
    pipeline_options(sp)
    sp.add_argument("--out", type=Path, default=Path("imupipe-out"))
    sp.add_argument("--executor", default="local", help="local (process pool) or dask (extra imupipe[dask])")
    sp.add_argument("--jobs", type=int, default=None, help="parallel jobs (default: number of cores)")
    exports(sp)
    blas(sp)
    strict(sp)
    common(sp)

    sp = sub.add_parser("status", help="say which stages of a pipeline are stale and why")
    sp.add_argument("sessions", type=Path, nargs="*", metavar="SESSION")
    pipeline_options(sp)
    sp.add_argument("--out", type=Path, default=Path("imupipe-out"))
    common(sp)

    sp = sub.add_parser("simulate", help="write a simulated calibration session with known truth")
    sp.add_argument("protocol")
    sp.add_argument("--effect", action="append", default=[], metavar="NAME=JSON",
                    help='an omitted-physics effect, e.g. --effect \'lever_arm={"r_m": [0.05, 0, 0]}\'')
    sp.add_argument("--param", action="append", default=[], metavar="KEY=JSON",
                    help="override a protocol parameter, e.g. --param n_positions=60")
    sp.add_argument("--imu", action="append", default=[], metavar="KEY=JSON",
                    help="override a sensor-model field, e.g. --imu rate_hz=200")
    sp.add_argument("--env", action="append", default=[], metavar="KEY=JSON",
                    help="override the environment, e.g. --env gravity_m_s2=9.80665 --env dip_deg=65")
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("--out", type=Path, default=None, help="output .mcap or .csv (default: <protocol>.mcap)")
    common(sp)

    sp = sub.add_parser("export", help="write a finished run's calibration for other software")
    sp.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="DIR/<session> of `imupipe run`")
    sp.add_argument("--format", action="append", required=True, metavar="FORMAT[,...]",
                    help="kalibr, imu_tk, px4, ardupilot, imu_calib")
    common(sp)

    common(sub.add_parser("plugins", help="list every plugin and what it provides"))
    common(sub.add_parser("pipelines", help="list the shipped pipelines, one line each"))
    return p


class _LineFormatter(logging.Formatter):
    """``imupipe: warning: <message>``: one line per record, like the error lines."""

    def format(self, record: logging.LogRecord) -> str:
        return f"imupipe: {record.levelname.lower()}: {one_line(record.getMessage(), 4 * MAX_LINE)}"


def _parse_assignments(option: str, items: list[str], example: str) -> dict[str, object]:
    """``NAME=JSON`` pairs of a repeated option, e.g. ``--effect lever_arm={"r_m": [0.05, 0, 0]}``."""
    parsed = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise ImupipeError(f"{option} {item!r}: expected NAME=JSON, e.g. {example}")
        try:
            parsed[name] = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ImupipeError(f"{option} {name}: value is not valid JSON ({exc.msg} at column {exc.colno})") from None
    return parsed


def _parse_effects(items: list[str]) -> dict[str, dict]:
    effects = _parse_assignments("--effect", items, 'lever_arm={"r_m": [0.05, 0, 0]}')
    for name, params in effects.items():
        if not isinstance(params, dict):
            raise ImupipeError(f"--effect {name}: parameters must be a JSON object")
    return effects


def _cmd_ingest(args) -> int:
    from .ingest import read_recording, write_recording
    from .plugins import make_registry

    registry = make_registry()
    recording = read_recording(args.session, registry)
    from .paths import safe_name

    out = args.out or Path(f"{safe_name(args.session.stem, 'session')}.tables")
    for path in write_recording(recording, out):
        print(path)
    return 0


def _cmd_plugins(args) -> int:
    from .plugins import make_registry

    registry = make_registry()
    rows: dict[tuple[str, str, str], list[str]] = {}
    for c in registry.all():
        rows.setdefault((c.plugin, c.distribution, c.dist_version), []).append(f"{c.kind[:-1]}:{c.name}")
    for (plugin, dist, ver), provides in sorted(rows.items()):
        print(f"{plugin}  ({dist or '-'} {ver or ''})".rstrip())
        print(f"    {', '.join(provides)}")
    for plugin, (dist, ver, why) in sorted(registry.broken.items()):
        print(f"{plugin}  ({dist or '-'} {ver or ''})  BROKEN".replace(" )", ")"))
        print(f"    {one_line(why)}")
    return 0


def _overrides(args) -> list[str]:
    """``--set`` items, and ``--device NAME`` as the override ``input.device``."""
    sets = list(getattr(args, "overrides", []) or [])
    if getattr(args, "device", None):
        sets.append(f"input.device={json.dumps(args.device)}")
    return sets


def _cmd_pipelines(args) -> int:
    import tomllib

    from .pipeline.config import shipped_pipelines

    rows = []
    for name, path in shipped_pipelines().items():
        try:
            text = str(tomllib.loads(path.read_text()).get("description", "")).strip()
        except (tomllib.TOMLDecodeError, UnicodeDecodeError):
            text = "(not valid TOML)"
        first = " ".join(re.split(r"(?<=[a-z0-9)])\.\s+(?=[A-Z])", text)[0].split()).rstrip(".")
        if len(first) > 100:  # one line: the first sentence up to its colon, else cut at a word
            head = first.split(": ")[0]
            first = head if len(head) <= 100 else first[:100].rsplit(" ", 1)[0].rstrip(",;:(") + " ..."
        rows.append((name, first or "(no description)"))
    width = max((len(n) for n, _ in rows), default=0)
    for name, line in rows:
        print(f"{name:<{width}}  {line}")
    return 0


def _cmd_run(args) -> int:
    from .pipeline.api import run_sessions
    from .verdict import read_verdict, strict_failure, verdict_lines

    verdicts = []
    for path in run_sessions(args.sessions, pipeline=args.pipeline, out=args.out, quiet=args.quiet,
                             export=args.export, overrides=_overrides(args),
                             blas_threads=args.blas_threads):
        verdicts.append(read_verdict(path))
        print(path)
        print("\n".join(verdict_lines(verdicts[-1])))
    return 3 if args.strict and strict_failure(verdicts) else 0


def _cmd_diagnose(args) -> int:
    import json

    from .pipeline.api import run_sessions
    from .verdict import read_verdict, strict_failure, verdict_lines

    pooled = None
    if len({p.resolve() for p in args.sessions}) > 1:
        from .pipeline.pooled import diagnose_sessions

        written, pooled = diagnose_sessions(args.sessions, pipeline=args.pipeline, out=args.out, quiet=args.quiet,
                                            overrides=_overrides(args))
    else:
        written = run_sessions(args.sessions[:1], pipeline=args.pipeline, out=args.out, quiet=args.quiet,
                               diagnose=True, overrides=_overrides(args))
    paths = [w.parent / "diagnosis.json" for w in written]
    if not paths or not all(p.exists() for p in paths):
        print(f"imupipe diagnose: error: {args.sessions[0]}: no diagnosis was written", file=sys.stderr)
        return 1
    for path in paths + ([pooled] if pooled else []):
        doc = json.loads(path.read_text())
        for f in doc["findings"]:
            print(f"{f['effect']} ({f['sensor']}, {f['regime']}): {f['explanation']}")
        if not doc["findings"]:
            print("no finding: the calibrated model explains the recording" + ("s together" if path == pooled else ""))
        print(path)
    verdicts = [read_verdict(w) for w in written]
    for verdict in verdicts:
        print("\n".join(verdict_lines(verdict)))
    return 3 if args.strict and strict_failure(verdicts) else 0


def _cmd_batch(args) -> int:
    from .pipeline.api import batch

    failures = batch(args.inputs, pipeline=args.pipeline, out=args.out, executor=args.executor,
                     jobs=args.jobs, quiet=args.quiet, export=args.export, overrides=_overrides(args),
                     strict=args.strict, blas_threads=args.blas_threads)
    if any(r.status != "ok" for r in failures):
        return 2
    return 3 if failures else 0


def _cmd_status(args) -> int:
    from .pipeline.api import status

    print(status(args.sessions, pipeline=args.pipeline, out=args.out, overrides=_overrides(args)))
    return 0


def _cmd_export(args) -> int:
    from .pipeline.export import export_run_dir, parse_formats
    from .plugins import make_registry

    registry = make_registry()
    for path in export_run_dir(args.run_dir, parse_formats(args.format, registry), registry):
        print(path)
    return 0


def _cmd_simulate(args) -> int:
    from .sim.api import simulate

    out = args.out or Path(f"{args.protocol}.mcap")
    params = _parse_assignments("--param", args.param, "n_positions=60")
    imu = _parse_assignments("--imu", args.imu, "rate_hz=200")
    env = _parse_assignments("--env", args.env, "gravity_m_s2=9.80665")
    for path in simulate(args.protocol, effects=_parse_effects(args.effect), seed=args.seed, out=out,
                         quiet=args.quiet, params=params, imu=imu, env=env):
        print(path)
    return 0


COMMANDS = {"ingest": _cmd_ingest, "run": _cmd_run, "batch": _cmd_batch, "status": _cmd_status,
            "simulate": _cmd_simulate, "plugins": _cmd_plugins, "export": _cmd_export,
            "pipelines": _cmd_pipelines, "diagnose": _cmd_diagnose}


MAX_LINE = 1500  # characters of an error line; an echoed value beyond is cut from its middle


def one_line(text: str, limit: int = MAX_LINE) -> str:
    """``text`` on one line, at most about ``limit`` characters (an echoed value may be
    megabytes): the middle is cut, so the start (file, problem) and the end (the fix) stay."""
    text = " ".join(str(text).split())
    if len(text) > limit:
        head, tail = text[: limit * 2 // 3], text[-(limit // 3):]
        text = f"{head} ... ({len(text) - len(head) - len(tail)} characters cut) ... {tail}"
    return text


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Python warnings outside the stages as one ``imupipe: warning:`` line each."""
    log.warning("%s", one_line(str(message)))


def _is_write_refused(exc: BaseException) -> bool:
    import errno

    return isinstance(exc, OSError) and exc.errno in (
        errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENAMETOOLONG)


# numpy asks the kernel for transparent huge pages on its large arrays; where the kernel then
# compacts memory synchronously on the fault (THP defrag "madvise", the common default), a fresh
# page costs more than the larger pages save (docs/pipelines.md#huge-pages). Set before numpy is
# imported, so batch workers inherit it; a value the user set is kept.
NUMPY_HUGEPAGE_ENV = "NUMPY_MADVISE_HUGEPAGE"


def main(argv: list[str] | None = None) -> int:
    import os
    import warnings

    os.environ.setdefault(NUMPY_HUGEPAGE_ENV, "0")
    args = _parser().parse_args(argv)
    handler = logging.StreamHandler()
    handler.setLevel(logging.WARNING)  # also for libraries that raise their own loggers' levels
    handler.setFormatter(_LineFormatter())
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        # numpy's floating-point complaints (divide by zero, ...) are symptoms, never the news:
        # the error line or the result's own checks say what is wrong
        warnings.filterwarnings("ignore", category=RuntimeWarning,
                                message=r"(invalid value|divide by zero|overflow|underflow) "
                                        r"encountered|Mean of empty slice|Degrees of freedom")
        try:
            return COMMANDS[args.command](args)
        except ImupipeError as exc:
            print(f"imupipe {args.command}: error: {one_line(exc)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("imupipe: interrupted", file=sys.stderr)
            return 130
        except BrokenPipeError:  # the reader of our output went away (``| head``)
            with contextlib.suppress(OSError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 0
        except RecursionError:
            print(f"imupipe {args.command}: error: input nested too deeply to read (a "
                  "self-referencing or absurdly deep file); simplify it", file=sys.stderr)
            return 2
        except Exception as exc:
            if _is_write_refused(exc):  # a full disk, a read-only or forbidden folder: the user's
                where = f"{exc.filename}: " if exc.filename else ""
                print(f"imupipe {args.command}: error: {one_line(where + (exc.strerror or str(exc)))}"
                      "; free space or give a folder you can write with --out", file=sys.stderr)
                return 2
            if os.environ.get("IMUPIPE_TRACEBACK"):
                raise
            print(f"imupipe {args.command}: internal error: {one_line(f'{type(exc).__name__}: {exc}')}"
                  " (a bug in imupipe or a plugin; rerun with IMUPIPE_TRACEBACK=1 for the "
                  "traceback and report it)", file=sys.stderr)
            return 1


if __name__ == "__main__":
    sys.exit(main())

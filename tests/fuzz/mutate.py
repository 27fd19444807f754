"""Mutated session files for the fault campaign (issue 12): one ``Case`` per mutation.

A case is laid out in a sandbox folder::

    <sandbox>/in/...        the session (and manifest, pipeline) the case made
    <sandbox>/out/          what ``imupipe`` is told to write into (--out)
    <sandbox>/*             decoys an escaping write would overwrite (report.md, accel.arrow, ...)

``Case.expect`` says what a correct imupipe does with it: ``"bad"`` (exit 2
with one line), ``"good"`` (exit 0) or ``"either"`` (a mutation that may leave a
usable recording: exit 0 or 2). Used by ``tests/fuzz/test_fuzz.py`` (hypothesis,
small) and ``bench/fuzz.py`` (the campaign).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DECOYS = ("report.md", "calibration.json", "accel.arrow", "figures/fit.png", "run.json")


@dataclass
class Case:
    name: str
    expect: str  # bad | good | either
    session: str  # relative to <sandbox>/in
    pipeline: str | None = None  # relative to <sandbox>/in
    command: str = "run"
    notes: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- a canonical CSV


@dataclass
class Csv:
    """A canonical CSV as header + rows of text fields (mutations work on either)."""

    header: list[str]
    rows: list[list[str]]

    @classmethod
    def parse(cls, text: str) -> Csv:
        lines = [line for line in text.splitlines() if line.strip()]
        return cls(lines[0].split(","), [line.split(",") for line in lines[1:]])

    def text(self) -> str:
        return "\n".join([",".join(self.header)] + [",".join(r) for r in self.rows]) + "\n"

    def cols(self, prefix: str) -> list[int]:
        return [i for i, h in enumerate(self.header) if h.startswith(prefix)]

    def scale(self, idx: list[int], factor: float, integer: bool = False) -> None:
        for r in self.rows:
            for i in idx:
                v = float(r[i]) * factor
                r[i] = str(int(v)) if integer else repr(v)


def tiny_csv(n: int = 400, rate_hz: float = 100.0, seed: int = 0) -> str:
    """A small canonical CSV (accel, gyro, mag, temperature) for the fast in-suite subset."""
    rng = np.random.default_rng(seed)
    t = 1_000_000_000 + np.arange(n) * int(1e9 / rate_hz)
    cols = {"t_ns": t}
    base = {"accel": (0.0, 0.0, 9.81), "gyro": (0.0, 0.0, 0.0), "mag": (2e-5, 0.0, 4e-5)}
    for s, b in base.items():
        for k, a in enumerate("xyz"):
            cols[f"{s}_{a}"] = b[k] + (1e-7 if s == "mag" else 0.01) * rng.standard_normal(n)
    cols["temperature"] = 25.0 + 0.01 * rng.standard_normal(n)
    header = list(cols)
    rows = [[str(int(t[i]))] + [repr(float(cols[h][i])) for h in header[1:]] for i in range(n)]
    return Csv(header, rows).text()


# --------------------------------------------------------------------------- mutations

Mutation = Callable[[np.random.Generator, Path, str, bytes], Case]
MUTATIONS: dict[str, Mutation] = {}


def mutation(fn: Mutation) -> Mutation:
    MUTATIONS[fn.__name__] = fn
    return fn


def _write(folder: Path, name: str, data: bytes | str) -> str:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        path.write_text(data, encoding="utf-8")
    else:
        path.write_bytes(data)
    return name


def _csv_case(name: str, expect: str, fn) -> Mutation:
    def make(rng, folder, suffix, data):
        if suffix != ".csv":
            return _write_case(rng, folder, suffix, data)
        table = Csv.parse(data.decode("utf-8"))
        fn(rng, table)
        return Case(name, expect, _write(folder, f"s{suffix}", table.text()))

    make.__name__ = name
    return make


def _write_case(rng, folder, suffix, data):  # the unmutated session (a mutation not for this format)
    return Case("clean", "good", _write(folder, f"s{suffix}", data))


@mutation
def truncate(rng, folder, suffix, data):
    cut = int(rng.integers(0, len(data)))
    return Case("truncate", "either", _write(folder, f"s{suffix}", data[:cut]), notes={"cut": cut})


@mutation
def bit_flips(rng, folder, suffix, data):
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        i = int(rng.integers(0, len(b)))
        b[i] ^= 1 << int(rng.integers(0, 8))
    return Case("bit_flips", "either", _write(folder, f"s{suffix}", bytes(b)))


@mutation
def zeroed_region(rng, folder, suffix, data):
    b = bytearray(data)
    i = int(rng.integers(0, len(b)))
    n = int(rng.integers(1, max(2, len(b) // 20)))
    b[i:i + n] = bytes(len(b[i:i + n]))
    return Case("zeroed_region", "either", _write(folder, f"s{suffix}", bytes(b)))


def _burst(value: str):
    def fn(rng, t: Csv):
        cols = t.cols(str(rng.choice(["accel", "gyro", "mag"])))
        i = int(rng.integers(0, len(t.rows) - 5))
        for r in t.rows[i:i + int(rng.integers(1, 5))]:
            r[int(rng.choice(cols))] = value
    return fn


def _reverse(rng, t: Csv):
    i = int(rng.integers(1, len(t.rows) - 10))
    t.rows[i:i + 10] = t.rows[i:i + 10][::-1]


def _jump_back(rng, t: Csv):
    i = int(rng.integers(1, len(t.rows)))
    for r in t.rows[i:]:
        r[0] = str(int(r[0]) - 10**12)


def _jump_forward(rng, t: Csv):
    i = int(rng.integers(1, len(t.rows)))
    for r in t.rows[i:]:
        r[0] = str(int(r[0]) + int(rng.choice([10**9, 10**11, 10**13])))


def _duplicate(rng, t: Csv):
    i = int(rng.integers(0, len(t.rows)))
    t.rows.insert(i, list(t.rows[i]))


def _wrap(rng, t: Csv):  # a 32-bit microsecond clock wrapping: time drops by 2^32 us
    i = int(rng.integers(1, len(t.rows)))
    for r in t.rows[i:]:
        r[0] = str(int(r[0]) - 2**32 * 1000)


def _constant(rng, t: Csv):
    cols = t.cols(str(rng.choice(["accel", "gyro"])))
    for r in t.rows:
        for i in cols:
            r[i] = "0.5"


def _dead_axis(rng, t: Csv):
    i = int(rng.choice(t.cols(str(rng.choice(["accel", "gyro"])))))
    for r in t.rows:
        r[i] = "0.0"


def _saturate(rng, t: Csv):
    cols = t.cols(str(rng.choice(["accel", "gyro"])))
    limit = float(rng.choice([0.01, 0.5, 2.0]))
    for r in t.rows:
        for i in cols:
            r[i] = repr(min(max(float(r[i]), -limit), limit))


def _unit(kind: str):
    def fn(rng, t: Csv):
        if kind == "time_x1000":
            t.scale([0], 1000.0, integer=True)
        elif kind == "time_div1000":
            t.scale([0], 1e-3, integer=True)
        elif kind == "time_1hz":
            t.rows = t.rows[:: max(1, len(t.rows) // 300)]
            t.scale([0], 100.0, integer=True)
        elif kind == "gyro_deg":
            t.scale(t.cols("gyro"), 180 / math.pi)
        elif kind == "accel_g":
            t.scale(t.cols("accel"), 1 / 9.80665)
        elif kind == "huge":
            t.scale(t.cols(str(rng.choice(["accel", "gyro", "mag"]))), 1e300)
        elif kind == "mag_ut":
            t.scale(t.cols("mag"), 1e6)
    return fn


def _swap_axes(rng, t: Csv):  # two gyro columns exchanged (a reader's or logger's axis mix-up)
    i, j = (int(c) for c in rng.choice(t.cols("gyro"), 2, replace=False))
    for r in t.rows:
        r[i], r[j] = r[j], r[i]


def _flip_axis(rng, t: Csv):  # one accelerometer axis sign-flipped
    i = int(rng.choice(t.cols("accel")))
    for r in t.rows:
        r[i] = repr(-float(r[i]))


def _bom_blank(rng, t: Csv):
    t.header[0] = "\ufeff" + t.header[0]
    t.rows.append([""])  # rendered as a blank line at the end


def _garbage_row(rng, t: Csv):
    i = int(rng.integers(0, len(t.rows)))
    t.rows[i] = [str(rng.choice(["abc", "", "1e999", "--", "0x10"]))] * len(t.header)


def _ragged(rng, t: Csv):
    i = int(rng.integers(0, len(t.rows)))
    t.rows[i] = t.rows[i][: int(rng.integers(1, len(t.header)))]


for _name, _expect, _fn in [
    ("nan_burst", "bad", _burst("nan")),
    ("inf_burst", "bad", _burst("inf")),
    ("time_reversal", "bad", _reverse),
    ("time_jump_back", "bad", _jump_back),
    ("time_jump_forward", "either", _jump_forward),
    ("duplicate_row", "bad", _duplicate),
    ("clock_wrap", "bad", _wrap),
    ("constant", "either", _constant),
    ("dead_axis", "either", _dead_axis),
    ("saturated", "either", _saturate),
    ("time_x1000", "bad", _unit("time_x1000")),
    ("time_div1000", "either", _unit("time_div1000")),
    ("time_1hz", "bad", _unit("time_1hz")),
    ("gyro_deg", "either", _unit("gyro_deg")),
    ("accel_g", "either", _unit("accel_g")),
    ("mag_ut", "either", _unit("mag_ut")),
    ("huge_values", "bad", _unit("huge")),
    ("swap_gyro_axes", "either", _swap_axes),  # exit 0 with a failing verdict, or refused
    ("flip_accel_axis", "either", _flip_axis),
    ("bom_blank_lines", "good", _bom_blank),
    ("garbage_row", "bad", _garbage_row),
    ("ragged_row", "bad", _ragged),
]:
    MUTATIONS[_name] = _csv_case(_name, _expect, _fn)


HOSTILE_STEMS = ["..", ".", "...", "a b", "-rf", "x" * 200, "ü_名前", ".hidden", "a\\b", "con"]


@mutation
def hostile_name(rng, folder, suffix, data):
    stem = ".." if rng.random() < 0.3 else str(rng.choice(HOSTILE_STEMS))
    return Case("hostile_name", "good", _write(folder, f"{stem}{suffix}", data),
                notes={"stem": stem})


HOSTILE_DEVICES = ["..", "a/b", "a_b", "../../x", "/", "", ".", "A_B"]


@mutation
def hostile_devices(rng, folder, suffix, data):
    """A manifest naming the same data under devices whose names try to leave --out."""
    if suffix != ".csv":
        return _write_case(rng, folder, suffix, data)
    table = Csv.parse(data.decode("utf-8"))
    streams = []
    devices = [".."] if rng.random() < 0.3 else []  # the one that escaped before issue 12
    devices += [str(d) for d in rng.choice([d for d in HOSTILE_DEVICES if d not in devices],
                                           size=2 - len(devices), replace=False)]
    for d in devices:
        for s in ("accel", "gyro"):
            sub = Csv(["t", "x", "y", "z"], [[r[0]] + [r[i] for i in table.cols(s)] for r in table.rows])
            _write(folder, f"{s}.csv", sub.text())
            streams.append(f'[[streams]]\nstream = "{s}"\nfile = "{s}.csv"\ntime_unit = "ns"\n'
                           f'device = {_toml_str(d)}\n')
    manifest = _write(folder, "m/session.toml", '[session]\nname = "h"\n' + "".join(
        s.replace('file = "', 'file = "../') for s in streams))
    command = "ingest" if rng.random() < 0.7 else "run"
    return Case("hostile_devices", "either", manifest, command=command,
                notes={"devices": devices})


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


@mutation
def deep_manifest(rng, folder, suffix, data):
    depth = int(rng.choice([500, 2000, 10000]))
    text = '[session]\nname = "d"\n[meta]\nx = ' + "[" * depth + "]" * depth + "\n"
    return Case("deep_manifest", "bad", _write(folder, "d/session.toml", text))


@mutation
def deep_pipeline(rng, folder, suffix, data):
    depth = int(rng.choice([500, 2000, 10000]))
    pipeline = _write(folder, "deep.toml", "x = " + "{a = " * depth + "1" + "}" * depth + "\n")
    return Case("deep_pipeline", "bad", _write(folder, f"s{suffix}", data), pipeline=pipeline)


@mutation
def self_reference(rng, folder, suffix, data):
    a = '[session]\nname = "a"\n[[streams]]\nstream = "accel"\nfile = "{}"\nreader = "session"\n'
    _write(folder, "r/b.toml", a.replace('"a"', '"b"').format("session.toml"))
    target = str(rng.choice(["session.toml", "b.toml"]))
    return Case("self_reference", "bad", _write(folder, "r/session.toml", a.format(target)))


def _accel_csv(folder, name: str, data: bytes) -> None:
    """The accelerometer columns of a session CSV as a t, x, y, z CSV at ``folder/name``."""
    table = Csv.parse(data.decode("utf-8"))
    _write(folder, name, Csv(["t", "x", "y", "z"],
                             [[r[0]] + [r[i] for i in table.cols("accel")] for r in table.rows]).text())


@mutation
def nan_sections(rng, folder, suffix, data):
    if suffix != ".csv":
        return _write_case(rng, folder, suffix, data)
    _accel_csv(folder, "n/a.csv", data)
    bound = str(rng.choice(["nan", "inf", "-inf", "1e30"]))
    text = ('[session]\nname = "n"\n[[streams]]\nstream = "accel"\nfile = "a.csv"\n'
            f'time_unit = "ns"\n[sections]\nitems = {{ rest = [{bound}, 10] }}\n')
    return Case("nan_sections", "bad", _write(folder, "n/session.toml", text), command="ingest")


@mutation
def triad_as_temperature(rng, folder, suffix, data):
    if suffix != ".csv":
        return _write_case(rng, folder, suffix, data)
    _accel_csv(folder, "t/a.csv", data)
    text = ('[session]\nname = "t"\n[[streams]]\nstream = "accel"\nfile = "a.csv"\n'
            'time_unit = "ns"\n[[streams]]\nstream = "temperature"\nfile = "a.csv"\n'
            'time_unit = "ns"\n')
    return Case("triad_as_temperature", "bad", _write(folder, "t/session.toml", text),
                command="ingest")


@mutation
def symlink_loop(rng, folder, suffix, data):
    link = folder / f"loop{suffix}"
    os.symlink(link.name, link)
    return Case("symlink_loop", "bad", link.name)


@mutation
def fifo(rng, folder, suffix, data):
    path = folder / f"pipe{suffix}"
    os.mkfifo(path)
    return Case("fifo", "bad", path.name)


@mutation
def empty(rng, folder, suffix, data):
    return Case("empty", "bad", _write(folder, f"s{suffix}", b""))


# mutations that work on any format's bytes (the others need a canonical CSV base)
ANY_FORMAT = ("truncate", "bit_flips", "zeroed_region", "hostile_name", "symlink_loop", "fifo",
              "empty", "deep_pipeline", "deep_manifest", "self_reference")


def make_case(kind: str, rng: np.random.Generator, sandbox: Path, base: Path) -> Case:
    """Lay out case ``kind`` of ``base`` (a session file) in ``sandbox``; return it."""
    folder = sandbox / "in"
    folder.mkdir(parents=True, exist_ok=True)
    (sandbox / "out").mkdir(exist_ok=True)
    for decoy in DECOYS:
        for where in (sandbox, folder):
            p = where / decoy
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text("decoy")
    return MUTATIONS[kind](rng, folder, base.suffix.lower(), base.read_bytes())


def snapshot(sandbox: Path) -> dict[str, tuple[int, int]]:
    """Every path under ``sandbox`` outside ``out/``: (size, mtime_ns), links not followed."""
    out = {}
    for root, dirs, files in os.walk(sandbox, followlinks=False):
        rel = Path(root).relative_to(sandbox)
        if rel == Path("."):
            dirs[:] = [d for d in dirs if d != "out"]
        for name in dirs + files:
            p = Path(root) / name
            try:
                st = p.lstat()
            except FileNotFoundError:
                continue
            out[str(rel / name)] = (st.st_size if not p.is_dir() else 0, st.st_mtime_ns)
    return out


def half_written(out: Path) -> list[str]:
    """Files under ``out`` a reader would take for finished but are not (or ``.part`` left)."""
    import json

    import pyarrow as pa
    from pyarrow import ipc

    bad = []
    for p in out.rglob("*"):
        name = p.name
        if name.endswith(".part") or name.startswith(".part-"):
            bad.append(f"{p}: left .part")
        elif p.is_file() and name.endswith(".json"):
            try:
                json.loads(p.read_text())
            except (ValueError, UnicodeDecodeError):
                bad.append(f"{p}: not JSON")
        elif p.is_file() and name.endswith(".arrow"):
            try:
                with pa.memory_map(str(p), "r") as f:
                    ipc.open_file(f).read_all()
            except (pa.ArrowInvalid, OSError):
                bad.append(f"{p}: not Arrow")
    return bad

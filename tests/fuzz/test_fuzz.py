"""A fast subset of the fault campaign (issue 12), driven by hypothesis; ``bench/fuzz.py`` runs
the full one. Any mutation of a small session, through ``imupipe ingest`` or ``run``: exit 0
or one error line with status 2, no traceback, nothing outside --out, nothing half-written."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mutate import MUTATIONS, half_written, make_case, snapshot, tiny_csv

from imupipe import cli


def _base(folder: Path) -> Path:
    path = folder / "base.csv"
    path.write_text(tiny_csv())
    return path


@settings(max_examples=30, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(sorted(MUTATIONS)), seed=st.integers(0, 2**16),
       command=st.sampled_from(["ingest", "run"]))
def test_mutated_session_is_handled(kind, seed, command):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        case = make_case(kind, np.random.default_rng(seed), tmp / "sandbox", _base(tmp))
        sandbox = tmp / "sandbox"
        before = snapshot(sandbox)
        argv = [case.command if case.command != "run" else command,
                str(sandbox / "in" / case.session), "--out", str(sandbox / "out"), "--quiet"]
        import contextlib
        import io

        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            import logging

            logging.getLogger().handlers.clear()  # main() logs to the stderr of this call
            code = cli.main(argv)
        text = err.getvalue()
        assert "Traceback" not in text and "internal error" not in text, text
        if case.expect == "bad":
            assert code == 2, (case, text)
        elif case.expect == "good" and argv[0] == "ingest":
            assert code == 0, (case, text)
        else:  # the tiny session is too short to calibrate: run may refuse it
            assert code in (0, 2), (case, text)
        if code == 2:
            lines = [line for line in text.splitlines() if line.strip()]
            assert " error: " in lines[-1], text
            assert not [ln for ln in lines[:-1] if "encountered" in ln], text  # numpy noise
        assert snapshot(sandbox) == before, case
        assert half_written(sandbox / "out") == [], case
        if code != 0:
            assert not list((sandbox / "out").rglob("calibration.json")), case

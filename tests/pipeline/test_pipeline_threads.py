"""imupipe sets its own BLAS threads (``imupipe/threads.py``): per process and per batch job."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from pipeline_toys import TOY_SPEC

from imupipe import cli
from imupipe.errors import ConfigError
from imupipe.pipeline import api
from imupipe.threads import BLAS_THREADS_ENV, blas_info, blas_threads, limited_blas


def test_thread_count_from_option_then_environment_then_one(monkeypatch):
    monkeypatch.delenv(BLAS_THREADS_ENV, raising=False)
    assert blas_threads() == 1
    monkeypatch.setenv(BLAS_THREADS_ENV, "3")
    assert blas_threads() == 3
    assert blas_threads(2) == 2  # the option wins
    monkeypatch.setenv(BLAS_THREADS_ENV, "many")
    with pytest.raises(ConfigError, match=r"\$IMUPIPE_BLAS_THREADS='many': expected a positive"):
        blas_threads()
    with pytest.raises(ConfigError, match="--blas-threads 0"):
        blas_threads(0)


def test_bad_variable_is_one_line_and_status_2(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv(BLAS_THREADS_ENV, "0")
    assert cli.main(["run", str(tmp_path / "x.mcap"), "--quiet", "--out", str(tmp_path)]) == 2
    assert "IMUPIPE_BLAS_THREADS='0'" in capsys.readouterr().err


def _in_fresh_process(code: str):
    """What ``code`` prints as JSON, run in a fresh process with the BLAS defaults (no thread
    variables set)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", BLAS_THREADS_ENV)}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    return json.loads(out.stdout)


def test_every_loaded_blas_is_limited_and_restored():
    """In a fresh process with the BLAS defaults (no OPENBLAS_NUM_THREADS): one thread per core."""
    code = (
        "import json, numpy, scipy.linalg\n"
        "from imupipe.threads import blas_info, limited_blas\n"
        "count = lambda: [i['num_threads'] for i in blas_info()]\n"
        "before = count()\n"
        "with limited_blas() as n:\n"
        "    inside = count()\n"
        "print(json.dumps([n, before, inside, count()]))\n"
    )
    n, before, inside, after = _in_fresh_process(code)
    assert n == 1
    assert len(inside) >= 2  # numpy's and SciPy's OpenBLAS are both loaded and limited
    assert inside == [1] * len(inside)
    assert after == before


def test_scipy_imported_inside_the_limit_is_limited_too():
    """The limit loads SciPy's OpenBLAS without importing scipy.linalg (a pipeline without the
    joint fit never needs it): scipy.linalg imported afterwards links to that library, limited."""
    code = (
        "import json, sys\n"
        "from imupipe.threads import blas_info, limited_blas\n"
        "with limited_blas() as n:\n"
        "    early = 'scipy.linalg' in sys.modules\n"
        "    import scipy.linalg\n"
        "    inside = [i['num_threads'] for i in blas_info()]\n"
        "print(json.dumps([early, inside]))\n"
    )
    early, inside = _in_fresh_process(code)
    assert len(inside) >= 2 and inside == [1] * len(inside)
    wheel_blas = list((Path(importlib.util.find_spec("scipy").origin).parent.parent / "scipy.libs")
                      .glob("libscipy_openblas*.so*"))
    assert early != bool(wheel_blas)  # loaded by itself where the wheel keeps it


def test_a_batch_job_runs_under_its_limit(monkeypatch, tmp_path, toy_pipeline, session):
    seen = []

    def fake_session(*args, **kwargs):
        seen.append(sorted({i["num_threads"] for i in blas_info()}))

    monkeypatch.setattr(api, "process_session", fake_session)
    monkeypatch.delenv(BLAS_THREADS_ENV, raising=False)
    job = api.Job(str(session), "s1", str(toy_pipeline), str(tmp_path / "out"), TOY_SPEC)
    assert api.run_job(job).status == "ok"
    with limited_blas(2):  # the job's own setting wins over what the caller had
        assert api.run_job(api.Job(*job.__dict__.values())).status == "ok"
    assert seen == [[1], [1]]
    assert api.run_job(api.Job(str(session), "s1", str(toy_pipeline), str(tmp_path / "out"),
                               TOY_SPEC, blas_threads=2)).status == "ok"
    assert seen[-1] == [2]  # threadpoolctl raises OpenBLAS's count too


@pytest.mark.parametrize("preset, expected", [(None, False), ("1", True)])
def test_the_command_turns_numpys_huge_pages_off_unless_the_user_set_them(preset, expected):
    """numpy reads NUMPY_MADVISE_HUGEPAGE when it is imported: the command sets it first."""
    probe = ("import imupipe.cli as cli, sys; cli.main(['pipelines']); import numpy as np; "
             "get = getattr(np._core.multiarray, '_get_madvise_hugepage', None); "
             "print('unknown' if get is None else get(), file=sys.stderr)")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if preset is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = preset
    got = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    if got.stderr.strip() == "unknown":
        pytest.skip("this numpy does not say whether it asks for huge pages")
    assert got.stderr.strip() == str(expected)

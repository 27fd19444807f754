"""bench/memory_timeline.py: its phases and timeline from RSS samples, and a run of a command."""

from __future__ import annotations

import sys

import pytest
from bench_scripts import load_bench


@pytest.fixture(scope="module")
def bench():
    return load_bench("memory_timeline")


def test_phases_end_where_memory_is_let_go(bench):
    samples = [(0.0, 100, "a"), (1.0, 300, "b"), (2.0, 290, "c"), (3.0, 150, "d"), (4.0, 320, "e"),
               (5.0, 310, "f"), (6.0, 120, "g")]
    assert bench.phases(samples, step=32, top=5) == [(4.0, 320, "e"), (1.0, 300, "b"), (6.0, 120, "g")]
    assert bench.changes(samples, step=32) == [(0.0, 100, "a"), (1.0, 300, "b"), (3.0, 150, "d"),
                                               (4.0, 320, "e"), (6.0, 120, "g")]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm")
def test_a_command_runs_under_the_sampler(bench, capsys):
    assert bench.main(["--every", "0.005", "pipelines"]) == 0
    out = capsys.readouterr().out
    assert "imupipe pipelines: exit 0" in out and "highest phases" in out
    assert bench.resident_mib() > 10

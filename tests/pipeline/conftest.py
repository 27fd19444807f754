"""Fixtures of the pipeline tests: toy sessions, toy pipelines, a registry counting stage runs."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # workers of a batch import the fixture plugin by name
    sys.path.insert(0, str(HERE))

import pipeline_toys

import imupipe.exporters
import imupipe.pipeline.executors
from imupipe.hookspecs import hookimpl
from imupipe.plugins import make_registry


class Counter:
    """Lifecycle observer: which stages ran and which came from the cache."""

    def __init__(self):
        self.ran: list[str] = []
        self.cached: list[str] = []
        self.before: list[str] = []

    @hookimpl
    def imupipe_before_stage(self, stage, key):
        self.before.append(stage)

    @hookimpl
    def imupipe_after_stage(self, stage, key, cached, seconds):
        (self.cached if cached else self.ran).append(stage)

    def reset(self):
        self.ran.clear()
        self.cached.clear()
        self.before.clear()


@pytest.fixture
def toy_registry():
    """``toy_registry(**variant) -> (registry, counter)``: a fresh registry per call."""

    def make(*extra, **variant):
        counter = Counter()
        registry = make_registry(
            [
                imupipe.exporters,
                imupipe.pipeline.executors,
                pipeline_toys.ToyPlugin(**variant),
                counter,
                *extra,
            ],
            entry_points_too=False,
        )
        return registry, counter

    return make


@pytest.fixture
def toy_pipeline(tmp_path) -> Path:
    path = tmp_path / "pipelines" / "toy.toml"
    path.parent.mkdir()
    path.write_text(pipeline_toys.TOY_PIPELINE)
    return path


@pytest.fixture
def session(tmp_path) -> Path:
    (tmp_path / "data").mkdir()
    return pipeline_toys.write_session(tmp_path / "data" / "s1.arrowsession", seed=1)

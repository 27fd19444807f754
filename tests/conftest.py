"""Shared fixtures: the real recordings in ../shared/data and the golden-file switch."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def pytest_configure(config):
    """The tests call imupipe's library in this process: its BLAS gets the one thread every
    imupipe process runs with (``imupipe/threads.py``), not a thread per core spinning on small
    blocks (the suite: 305 s of user CPU with the default, 202 s so, on 2 cores)."""
    from imupipe.threads import set_blas_threads

    set_blas_threads()


def pytest_addoption(parser):
    parser.addoption("--update-golden", action="store_true", default=False,
                     help="rewrite golden files from the current outputs instead of comparing")


@pytest.fixture
def update_golden(request) -> bool:
    return request.config.getoption("--update-golden")


@pytest.fixture
def shared_data() -> Path:
    """The real recordings of ../shared/data (skips when the checkout has none beside it)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"no shared data at {SHARED_DATA}")
    return SHARED_DATA

import os
import sys

import numpy as np
import pytest

from imupipe.heap import _malloc_trim, release_free_memory


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux") or _malloc_trim() is None, reason="glibc's malloc_trim")
def test_freed_arrays_pages_go_back_to_the_system():
    """Arrays below glibc's mmap threshold come from its heap, whose freed pages it keeps (the
    figures after a run's stages could not reuse them): released, the process shrinks."""
    arrays = [np.ones(8000) for _ in range(800)]  # 64 KB each: 50 MiB of heap
    later = np.ones(8000)  # above them: the heap's top cannot shrink by itself
    del arrays
    before = _rss_mib()
    release_free_memory()
    assert before - _rss_mib() > 30
    assert later.sum() == 8000

"""release_free_heap gives freed heap pages back: measured on this process's resident set (/proc)."""

import sys

import pytest

from pixmuscle.mechanics import heap


def _rss_MB() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


@pytest.mark.skipif(not sys.platform.startswith("linux") or heap._trim() is None, reason="glibc's malloc_trim")
def test_freed_heap_pages_leave_the_resident_set():
    # 3,000 blocks of 64 kB (below glibc's mmap threshold: they come from the heap), written so that
    # their pages are resident; all but the last freed, which keeps the heap's top in use, so that
    # glibc's own trimming at free cannot return them
    blocks = [b"\x01" * 65_536 for _ in range(3_000)]
    last = blocks[-1]
    del blocks
    before = _rss_MB()
    assert heap.release_free_heap()
    after = _rss_MB()
    assert before - after > 0.75 * 3_000 * 64 / 1024, (before, after)  # most of the 188 MB freed
    assert last[0] == 1


def test_without_glibc_it_does_nothing(monkeypatch):
    monkeypatch.setattr(heap, "_trim", lambda: None)
    assert heap.release_free_heap() is False

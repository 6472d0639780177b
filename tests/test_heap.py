"""world_model.train.heap: freed memory stays in the heap once retain_freed_memory ran (glibc only)."""

import platform
import subprocess
import sys
import textwrap

import pytest

from world_model.train.heap import HeapConfig, heap_retained, retain_freed_memory

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# 64 MB of 1 MB blocks, touched and freed, five times; prints the minor page faults of the last
# three rounds. glibc's default trims the freed heap top back to the OS after every round, so each
# round faults its 64 MB in again (~16k pages); a retained heap serves later rounds from memory
# it already has.
CHURN = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    from world_model.train.heap import retain_freed_memory
    if sys.argv[1] == "retain":
        assert retain_freed_memory()
    faults = 0
    for i in range(5):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        blocks = [np.ones(1 << 18, dtype=np.float32) for _ in range(64)]
        del blocks
        if i >= 2:
            faults += resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    print(faults)
    """
)


def _churn_faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", CHURN, mode], check=True, capture_output=True, text=True).stdout
    return int(out.split()[-1])


@pytest.mark.skipif(not GLIBC, reason="mallopt tuning is glibc-only")
def test_retained_heap_stops_page_faults_of_repeated_allocations():
    pages = 3 * 64 * (1 << 20) // 4096  # three rounds of 64 MB
    assert _churn_faults("default") > pages // 2  # the behaviour the setting exists for
    assert _churn_faults("retain") < pages // 20


@pytest.mark.skipif(not GLIBC, reason="mallopt tuning is glibc-only")
def test_retain_is_idempotent_and_reported():
    assert retain_freed_memory() and retain_freed_memory()
    assert heap_retained() == HeapConfig()


def test_retain_does_nothing_off_glibc(monkeypatch):
    import world_model.train.heap as heap

    monkeypatch.setattr(heap, "_applied", None)
    monkeypatch.setattr(heap, "_glibc", lambda: None)
    assert heap.retain_freed_memory() is False and heap.heap_retained() is None

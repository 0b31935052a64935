"""core/heap.py: large freed blocks kept in glibc's heap for the next frame, handed back when a run ends."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: A child process: after keep_freed_blocks (or not), where does a 64 MiB array live, and what does freeing it
#: and release_freed_blocks do to the resident set?  Prints "heap|mmap kept=<bool> rss_drop_mb=<float>".
CHILD = r"""
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np
from core.heap import keep_freed_blocks, release_freed_blocks

def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20

def in_heap(address):
    with open("/proc/self/maps") as f:
        for line in f:
            if line.rstrip().endswith("[heap]"):
                lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
                if lo <= address < hi:
                    return True
    return False

kept = keep_freed_blocks()
a = np.ones(8 << 20)  # 64 MiB, touched
where = "heap" if in_heap(a.ctypes.data) else "mmap"
b = np.ones(8 << 20)
del a
before = rss_mb()
release_freed_blocks()
print(where, "kept=%s" % kept, "rss_drop_mb=%.1f" % (before - rss_mb()))
"""


def _child(env_extra=None):
    env = dict(os.environ, **(env_extra or {}))
    out = subprocess.run([sys.executable, "-c", CHILD, str(REPO)], capture_output=True, text=True, env=env,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    where, kept, drop = out.stdout.split()
    return where, kept == "kept=True", float(drop.split("=")[1])


glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or not hasattr(__import__("ctypes").CDLL(None),
                                                                                "gnu_get_libc_version"),
                           reason="glibc only")


@glibc
def test_large_blocks_come_from_the_heap_and_go_back_when_released():
    """With freed blocks kept, a 64 MiB array is served from the heap (not a fresh mapping); once freed and
    released (malloc_trim), the resident set drops by about its size (it was freed below a live block: only
    malloc_trim hands it back)."""
    where, kept, drop = _child()
    assert kept and where == "heap"
    assert drop > 48.0


@glibc
def test_a_dask_workers_trim_setting_is_overridden():
    """distributed's nanny starts its workers with MALLOC_TRIM_THRESHOLD_=65536 (every array above 128 KiB mapped
    and unmapped anew: a flash task took 1.40-1.61 s in such a worker against 1.06-1.25 s without); the first frame
    sets glibc's thresholds all the same."""
    where, kept, drop = _child({"MALLOC_TRIM_THRESHOLD_": "65536"})
    assert kept and where == "heap"
    assert drop > 48.0


@glibc
def test_turned_off_by_the_environment():
    """LADAR_KEEP_FREED_MEMORY=0: glibc's defaults stay (a 64 MiB array is its own mapping), nothing is released."""
    where, kept, drop = _child({"LADAR_KEEP_FREED_MEMORY": "0"})
    assert not kept and where == "mmap"
    assert abs(drop) < 8.0


def test_other_c_libraries_are_left_alone(monkeypatch):
    """Where the C library is not glibc nothing is changed and release does nothing."""
    import core.heap as heap

    monkeypatch.setattr(heap, "_state", {"checked": False, "kept": False, "libc": None})
    monkeypatch.setattr(heap, "_glibc", lambda: None)
    assert heap.keep_freed_blocks() is False
    heap.release_freed_blocks()  # no C library call
    assert heap._state == {"checked": True, "kept": False, "libc": None}

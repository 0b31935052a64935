"""Whole-suite settings.  ``scripts/test.sh`` runs the suite on two pytest-xdist workers, each test file whole on
one worker (``--dist loadfile``: module fixtures and a file's own order, e.g. a "the runs left the committed files
alone" check after the runs, stay as in a serial run).  Files are handed out in the order collected here: under
xdist the files that take longest go first (longest-first keeps the two workers busy until the end instead of one
waiting on a late slow file); a serial run keeps pytest's own order.

The suite's compiled kernels go to ``build/kernel-cache/`` of this checkout (git-ignored, not part of the
extension: ``scripts/blender_env.PACKAGE_PATHS``), unless ``LADAR_KERNEL_CACHE`` is set already; every test process
and every subprocess it starts (``scripts/ladar_run.py``, benchmarks, sweep workers) inherits the setting.  The
per-user cache keeps the 8 most recently used source digests (core/jit.py ``KEEP_CACHE_FOLDERS``): on a machine
where several checkouts with different core sources run tests at once, each one's digest was pruned by the
others' imports and the suite compiled its kernels again mid-run (seen: this checkout's folder re-created 11
minutes into a run).  Tests of the default location clear the variable themselves (tests/core/test_jit_cache.py).
"""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("LADAR_KERNEL_CACHE", str(REPO / "build" / "kernel-cache"))

#: Test files that take longest: seconds of their slowest tests in one serial run (``--durations=100``, the shared
#: 2-core machine at load 10-20, 3165 s in all).  A file not listed counts as quick; only the order in which the
#: files are handed to the workers depends on these figures.
SLOW_FILES = {
    "tests/core/sweep/test_sweep.py": 912.5,
    "tests/core/test_jit_cache.py": 393.8,
    "tests/test_bench_quick.py": 381.8,
    "tests/test_documented_commands.py": 266.2,
    "tests/addon/test_sweep_cluster.py": 137.9,
    "tests/addon/test_sweep_example.py": 132.7,
    "tests/core/engine/test_gate_coverage.py": 72.0,
    "tests/addon/test_sweep_blender.py": 68.0,
    "tests/addon/test_fault_injection.py": 62.0,
    "tests/addon/test_sequence.py": 60.0,
    "tests/core/physics/detection/test_noisy_kernels.py": 44.5,
    "tests/addon/test_cli.py": 39.6,
    "tests/core/test_jit_signals.py": 36.1,
    "tests/core/engine/test_memory_all_systems.py": 24.3,
    "tests/core/physics/detection/test_echo_detection.py": 21.5,
    "tests/core/engine/test_engine.py": 21.5,
    "tests/core/systems/test_profiler.py": 19.4,
    "tests/core/test_input_boundary.py": 18.8,
}


def _weight(item) -> float:
    path = item.nodeid.split("::", 1)[0]
    return SLOW_FILES.get(path, 0.0)


def pytest_collection_modifyitems(session, config, items):
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    # stable: the files' own test order is kept; ties keep pytest's file order
    items.sort(key=lambda item: -_weight(item))

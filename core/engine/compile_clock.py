"""Stage times without the kernels' compile time.

The first run in a process compiles (or, after a change of the core's source, recompiles) every numba kernel it
calls (core/jit.py), inside whichever stage first calls it: 50 s of "echoes" on a fresh install is compile time,
not echo detection.  numba announces every compilation (the ``"numba:compile"`` event, in the thread that
compiles); a listener adds the time of each outermost compilation to its thread's total.  :func:`stage_clock` is
``time.perf_counter()`` minus the calling thread's compile total: an interval measured with it in one thread is
that interval without the compilations that happened in it.  :func:`compile_seconds_total` is every thread's.
"""
from __future__ import annotations

import threading
import time

_local = threading.local()
_lock = threading.Lock()
_total = [0.0]
_installed = [False]


def _install() -> None:
    with _lock:
        if _installed[0]:
            return
        try:
            from numba.core import event
        except ImportError:  # pragma: no cover - numba is a requirement
            _installed[0] = True
            return

        class _CompileListener(event.Listener):
            def on_start(self, ev):
                depth = getattr(_local, "depth", 0)
                if depth == 0:
                    _local.start = time.perf_counter()
                _local.depth = depth + 1

            def on_end(self, ev):
                _local.depth = getattr(_local, "depth", 1) - 1
                if _local.depth == 0:
                    dt = time.perf_counter() - _local.start
                    _local.seconds = getattr(_local, "seconds", 0.0) + dt
                    with _lock:
                        _total[0] += dt

        event.register("numba:compile", _CompileListener())
        _installed[0] = True


def compile_seconds() -> float:
    """Seconds the calling thread has spent compiling kernels since the listener was installed."""
    return getattr(_local, "seconds", 0.0)


def compile_seconds_total() -> float:
    """Seconds all threads have spent compiling kernels since the listener was installed."""
    return _total[0]


def stage_clock() -> float:
    """``time.perf_counter()`` minus the calling thread's compile time (the listener is installed on first use)."""
    if not _installed[0]:
        _install()
    return time.perf_counter() - compile_seconds()

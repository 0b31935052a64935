"""Stage times without compile time (core/engine/compile_clock.py): a stage that compiles a kernel on first use
is timed without the compilation, in its own thread only; the run records the compile time apart."""
import threading
import time

import numpy as np
import pytest

from core.engine.compile_clock import compile_seconds, compile_seconds_total, stage_clock
from core.engine.frame import StageLog


def _fresh_kernel():
    from numba import njit

    @njit(cache=False)
    def k(x):  # a new function object each call: numba compiles it on its first call
        s = 0.0
        for i in range(x.shape[0]):
            s += np.sin(x[i]) * np.cos(x[i])
        return s

    return k


def test_a_stage_is_timed_without_the_compilation_it_triggers():
    stage_clock()  # the listener
    _fresh_kernel()(np.ones(2))  # numba's own first-use set-up (imports, LLVM) is not the stage's compilation
    kernel = _fresh_kernel()
    log = StageLog.of(("echoes",))
    c0, total0 = compile_seconds(), compile_seconds_total()
    with log.timed("echoes"):
        t = time.perf_counter()
        kernel(np.ones(10))
        time.sleep(0.05)  # the stage's own work
        wall = time.perf_counter() - t
    compiled = compile_seconds() - c0
    assert compiled > 0.02  # numba compiled the kernel in this thread (measured 0.1-0.5 s)
    assert compile_seconds_total() - total0 == pytest.approx(compiled, abs=1e-9)
    assert log.times["echoes"] == pytest.approx(wall - compiled, abs=5e-3)
    assert 0.05 <= log.times["echoes"] < 0.05 + 0.02


def test_compilation_in_another_thread_leaves_this_threads_clock_alone():
    stage_clock()
    kernel = _fresh_kernel()
    before, c_here = stage_clock(), compile_seconds()
    t0 = time.perf_counter()
    worker = threading.Thread(target=kernel, args=(np.ones(3),))
    worker.start()
    worker.join()
    assert compile_seconds() == c_here
    assert stage_clock() - before == pytest.approx(time.perf_counter() - t0, abs=5e-3)


def test_run_records_its_compile_time_and_the_summary_says_stages_exclude_it(tmp_path):
    from core.fileio.run_folder import run_summary
    from core.run import run_simulation
    from tests.core.scenes import config_for, plate

    path, res = run_simulation(plate(100.0, 5.0), np.eye(4), config_for(100.0, pixels=4), tmp_path / "r")
    kernels = res.stats["compile_times_s"]["kernels"]
    assert kernels >= 0.0
    assert "without compiling kernels on first use" in run_summary(path, res)

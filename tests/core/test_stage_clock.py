"""Stage times without kernel loading and compiling (core/jit.py stage_clock): a stage that compiles a kernel on
first use is timed without the compilation, in its own thread only; the run records the kernels apart
(metadata ``kernels``) and the summary says the stages exclude them."""
import threading
import time

import numpy as np
import pytest

from core.engine.frame import StageLog
from core.jit import kernel, kernel_report, kernel_seconds, stage_clock


def _fresh_kernel():
    @kernel
    def k(x):  # a new function object each call: numba compiles it on its first call (a test's kernel: not cached)
        s = 0.0
        for i in range(x.shape[0]):
            s += np.sin(x[i]) * np.cos(x[i])
        return s

    return k


def test_a_stage_is_timed_without_the_compilation_it_triggers():
    _fresh_kernel()(np.ones(2))  # numba's own first-use set-up (imports, LLVM) is not the stage's compilation
    k = _fresh_kernel()
    log = StageLog.of(("echoes",))
    c0, total0 = kernel_seconds(), kernel_report()["load_and_compile_s"]
    with log.timed("echoes"):
        t = time.perf_counter()
        k(np.ones(10))
        time.sleep(0.05)  # the stage's own work
        wall = time.perf_counter() - t
    compiled = kernel_seconds() - c0
    assert compiled > 0.02  # numba compiled the kernel in this thread (measured 0.1-0.5 s)
    assert kernel_report()["load_and_compile_s"] - total0 == pytest.approx(compiled, abs=1e-9)
    assert log.times["echoes"] == pytest.approx(wall - compiled, abs=5e-3)
    assert 0.05 <= log.times["echoes"] < 0.05 + 0.02


def test_compilation_in_another_thread_leaves_this_threads_clock_alone():
    k = _fresh_kernel()
    before, c_here = stage_clock(), kernel_seconds()
    t0 = time.perf_counter()
    worker = threading.Thread(target=k, args=(np.ones(3),))
    worker.start()
    worker.join()
    assert kernel_seconds() == c_here
    assert stage_clock() - before == pytest.approx(time.perf_counter() - t0, abs=5e-3)


def test_run_records_its_kernels_and_the_summary_says_stages_exclude_them(tmp_path):
    from core.fileio.run_folder import run_summary
    from core.run import run_simulation
    from tests.core.scenes import config_for, plate

    path, res = run_simulation(plate(100.0, 5.0), np.eye(4), config_for(100.0, pixels=4), tmp_path / "r")
    k = res.stats["kernels"]
    assert k["load_and_compile_s"] >= 0.0 and k["loaded"] >= 0 and k["compiled"] >= 0
    assert "without loading or compiling kernels" in run_summary(path, res)

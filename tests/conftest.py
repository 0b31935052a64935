"""Whole-suite settings.  ``scripts/test.sh`` runs the suite on two pytest-xdist workers, each test file whole on
one worker (``--dist loadfile``: module fixtures and a file's own order, e.g. a "the runs left the committed files
alone" check after the runs, stay as in a serial run).  Files are handed out in the order collected here: under
xdist the files that take longest go first, after :data:`FIRST_FILES` (longest-first keeps the two workers busy until
the end instead of one waiting on a late slow file); a serial run keeps pytest's own order.

The suite's compiled kernels go to ``build/kernel-cache/`` of this checkout (git-ignored, not part of the
extension: ``scripts/blender_env.PACKAGE_PATHS``), unless ``LADAR_KERNEL_CACHE`` is set already; every test process
and every subprocess it starts (``scripts/ladar_run.py``, benchmarks, sweep workers) inherits the setting.  The
per-user cache keeps the 8 most recently used source digests (core/jit.py ``KEEP_CACHE_FOLDERS``): on a machine
where several checkouts with different core sources run tests at once, each one's digest was pruned by the
others' imports and the suite compiled its kernels again mid-run (seen: this checkout's folder re-created 11
minutes into a run).  Tests of the default location clear the variable themselves (tests/core/test_jit_cache.py).

The hostile-input suite's attempt count (issue 31: at least 10,000 generated attempts, counted).

A test of the suite takes the ``hostile_attempts`` fixture and calls it once per attempt it makes (an input
generated, tried, and its outcome checked).  :data:`HOSTILE_FLOORS` holds the fewest attempts each such test
must make (checked when the test ends); their sum is at least :data:`HOSTILE_TOTAL_FLOOR`
(tests/core/test_fuzz_inputs.py checks).  The session's total is printed at the end of the test output, and a
session that ran every test of the suite with fewer attempts in all fails.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("LADAR_KERNEL_CACHE", str(REPO / "build" / "kernel-cache"))

#: The project's Python folders whose bytecode the session writes once, before any test (:func:`compile_project`).
BYTECODE_DIRS = ("core", "ladar_addon", "operators", "panels", "scripts", "bench")


def compile_project() -> None:
    """Write the bytecode (``__pycache__``, git-ignored, never packaged) of the project's modules that is missing
    or out of date.  Where ``PYTHONDONTWRITEBYTECODE`` is set (as on the shared development machine) Python reads
    bytecode but never writes it, so each of the suite's fresh processes (``scripts/ladar_run.py`` runs, benchmark
    and sweep processes: a few hundred) compiled every project source it imports again: 0.5 s of CPU a flash-demo
    run, 12 % of it (measured 4.4 s -> 3.9 s).  py_compile writes whatever that setting says, each file through a
    temporary file renamed into place (two sessions at once are safe); a file that does not compile is left to
    the test that imports it."""
    import compileall

    for name in BYTECODE_DIRS:
        compileall.compile_dir(REPO / name, quiet=2, workers=1)
    compileall.compile_file(REPO / "__init__.py", quiet=2)


def pytest_configure(config):
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # once a session: the controller, or the one process
        compile_project()
        base = _cpu_report_path()
        if base is not None:  # this session's report only
            for part in [base, *base.parent.glob(base.name + ".gw*")]:
                part.unlink(missing_ok=True)

#: Test files that take longest: the CPU seconds of their tests (the test process's and the child processes' it
#: waited for: ``scripts/ladar_run.py`` runs, benchmarks, Dask workers) in one run of the whole suite on two workers
#: (session 29: 1,901 tests, 774 s of CPU in the tests, 1,216 s wall at load 4-12 on the shared 2-core machine;
#: tests/test_documented_commands.py and tests/addon/test_sweep_example.py as after that session's merge of their
#: two runs of the README's sweep).  Session 31 measured the files marked "s31" one at a time (``/usr/bin/time``
#: of ``pytest FILE``: the test process and its waited-for children, kernels in ``build/kernel-cache/``, load 3-12).
#: Session 32 measured the files marked "s32" the same way, one at a time (load in the comment; kernels in
#: ``build/kernel-cache/``, filled, including the sweep workers' shipped core; ``LADAR_TEST_CPU_REPORT`` gives the
#: per-test split).  CPU rather than wall: under load the wall figures mostly measure the other jobs.  A file not
#: listed counts as quick; only the order in which the files are handed to the workers depends on these figures.
SLOW_FILES = {
    "tests/addon/test_fault_injection.py": 66.4,  # s32, load 3-5 (46.5 of it the kernels test's cold compiles)
    "tests/test_bench_quick.py": 81.6,  # s32, load 14 (170 with its sweep worker compiling the shipped core's kernels)
    "tests/addon/test_sweep_cluster.py": 58.7,  # s32, load 16 (255 with its workers compiling the shipped core's)
    # (session 31, measured on its own: the test functions' process CPU time, load average 8-10)
    "tests/core/physics/test_detector_weak_returns.py": 64.8,  # s32, load 16-19 (55.4 at load 8-10)
    "tests/core/sweep/test_sweep.py": 64.2,  # s32, load 10-18 (s31: 45.7)
    "tests/core/test_jit_cache.py": 44.2,  # s31
    "tests/test_validation_report.py": 85.3,  # s32, load 14-17, with the Mitsuba comparison (.venv-validation)
    "tests/addon/test_sweep_example.py": 36.2,  # s32, load 13-19
    "tests/test_documented_commands.py": 23.5,  # s32, load 14 (37.4 before validate_atmosphere ran --smallest)
    "tests/addon/test_sweep_blender.py": 27.8,  # s32, load 14-17 (s31: 24.4)
    "tests/addon/test_cli.py": 22.2,  # s31 (about 56 before its second-run kernel test moved, 34.0 s alone)
    "tests/core/atmosphere/test_weather.py": 26.3,  # s32, load 13-15
    "tests/addon/test_cli_hostile_input.py": 16.9,  # s32, load 15
    "tests/core/test_fuzz_inputs.py": 14.0,
    "tests/core/physics/test_detector_models.py": 11.7,
    "tests/test_sensor_table.py": 10.6,
    "tests/addon/test_modal.py": 10.1,
    "tests/core/test_sensor_presets.py": 10.1,
    "tests/core/test_jit_signals.py": 10.1,
    "tests/core/test_jit_shared.py": 16.4,  # s32 (alone, load 6-14; its 8 probe processes)
    "tests/addon/test_progress_heartbeat.py": 10.1,
    "tests/core/atmosphere/test_aerosol_layers.py": 9.8,
    "tests/addon/test_sample_views.py": 9.1,
    "tests/addon/test_sequence.py": 8.9,  # s31 (26.8 with the PNG previews of every run)
    "tests/addon/test_readme_examples.py": 8.2,
    "tests/addon/test_results.py": 8.0,  # s31 (13.3 with the PNG previews of every run)
    "tests/addon/test_simulate.py": 7.3,  # s31 (9.8 with the PNG previews of every run)
    "tests/addon/test_run_safety.py": 6.9,  # s31 (12.0 with the PNG previews of every run)
    "tests/core/fileio/test_full_disk.py": 6.7,
    "tests/core/physics/test_solar_background.py": 6.6,
    "tests/core/fileio/test_ply_clients.py": 5.8,
    "tests/core/atmosphere/test_scintillation.py": 5.8,
    "tests/core/test_input_boundary.py": 5.7,
    "tests/core/atmosphere/test_wave_optics_scintillation.py": 5.6,
    "tests/addon/test_systems.py": 5.5,
    "tests/core/atmosphere/test_atmosphere.py": 5.1,
}

#: Handed out before every other file whatever its figure: tests/addon/test_cli.py's first test is the warm-up
#: (``scripts/ladar_run.py warm-up``), which with an empty ``build/kernel-cache/`` compiles every system's kernels
#: once, early, for the ``scripts/ladar_run.py`` runs of the other files that share that cache.
FIRST_FILES = ("tests/addon/test_cli.py",)


def _weight(item) -> float:
    path = item.nodeid.split("::", 1)[0]
    return math.inf if path in FIRST_FILES else SLOW_FILES.get(path, 0.0)


def pytest_collection_modifyitems(session, config, items):
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    # stable: the files' own test order is kept; ties keep pytest's file order
    items.sort(key=lambda item: -_weight(item))


#: ``LADAR_TEST_CPU_REPORT=FILE``: where the suite's CPU goes, one JSON line per test (:func:`pytest_runtest_protocol`)
#: in ``FILE`` (``FILE.gw0``, ``FILE.gw1`` … from the xdist workers), and the files that took most printed at the
#: end (:func:`cpu_report_lines`).  Off unless set: an audit hook costs every process start a function call.
CPU_REPORT_ENV = "LADAR_TEST_CPU_REPORT"
_launched: list[str] = []


def _audit(event: str, args) -> None:
    """Counts the processes a test starts: ``subprocess.Popen`` (and run, check_output …), ``os.posix_spawn``
    and ``os.fork``.  Not multiprocessing's "spawn" processes (a Dask LocalCluster's workers): Python raises no
    audit event for them; their CPU time still counts, in the children's, once they have been waited for."""
    if event == "subprocess.Popen":
        argv = args[1]
        _launched.append(" ".join(map(str, argv)) if isinstance(argv, (list, tuple)) else str(argv))
    elif event in ("os.posix_spawn", "os.fork"):
        _launched.append(f"<{event}>")


def _cpu_report_path() -> Path | None:
    value = os.environ.get(CPU_REPORT_ENV)
    if not value:
        return None
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    return Path(f"{value}.{worker}") if worker else Path(value)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """With :data:`CPU_REPORT_ENV` set: each test's wall time, this process's CPU time (every thread's) and the CPU
    time of the child processes it waited for (``RUSAGE_CHILDREN``: ``scripts/ladar_run.py`` runs, benchmarks,
    Dask workers once stopped), set-up and tear-down included (a module fixture's cost lands on the test that
    built or tore it down), and the processes it started."""
    path = _cpu_report_path()
    if path is None:
        yield
        return
    import json
    import resource
    import sys
    import time

    if not getattr(_audit, "installed", False):
        sys.addaudithook(_audit)
        _audit.installed = True
    n0 = len(_launched)
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    yield
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    row = {"test": item.nodeid, "wall_s": round(time.perf_counter() - wall0, 3),
           "cpu_s": round(time.process_time() - cpu0, 3),
           "children_cpu_s": round(max(0.0, c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime), 3),
           "processes": [cmd[:300] for cmd in _launched[n0:]], "load_1min": round(os.getloadavg()[0], 2)}
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(row) + "\n")


def cpu_report_lines(base: Path, top: int = 15) -> list[str]:
    """The files whose tests took most CPU (their own and their children's), from the JSON lines of ``base`` and
    ``base.gw*``: one line each, then the session's totals."""
    import json

    files: dict[str, list[float]] = {}
    for part in sorted(base.parent.glob(base.name + "*")):
        if part.name != base.name and not part.name[len(base.name):].startswith(".gw"):
            continue
        for line in part.read_text(encoding="utf-8").splitlines():
            row = json.loads(line)
            t = files.setdefault(row["test"].split("::", 1)[0], [0.0, 0.0, 0.0, 0])
            t[0] += row["cpu_s"]
            t[1] += row["children_cpu_s"]
            t[2] += row["wall_s"]
            t[3] += len(row["processes"])
    ranked = sorted(files.items(), key=lambda kv: -(kv[1][0] + kv[1][1]))
    out = [f"{cpu + child:7.1f} s CPU ({cpu:.1f} tests, {child:.1f} children), {wall:6.1f} s wall, "
           f"{n} processes started  {name}" for name, (cpu, child, wall, n) in ranked[:top]]
    total = [sum(v[i] for v in files.values()) for i in range(4)]
    out.append(f"{total[0] + total[1]:7.1f} s CPU ({total[0]:.1f} tests, {total[1]:.1f} children), "
               f"{total[2]:6.1f} s wall, {total[3]} processes started  in all ({len(files)} files)")
    return out


#: test function -> fewest generated attempts it makes (tests/core/test_fuzz_inputs.py,
#: tests/addon/test_cli_hostile_input.py)
HOSTILE_FLOORS = {
    # in-process, at the validation layer (tests/core/test_fuzz_inputs.py)
    "test_mutated_config_fields_are_accepted_or_refused_cleanly": 100,
    "test_mutated_materials_and_schema_version": 100,
    "test_corrupt_config_files_are_refused_cleanly": 100,
    "test_malformed_scene_arrays_are_refused_cleanly": 100,
    "test_what_is_not_a_config_is_refused_cleanly": 60,
    "test_config_from_dict_of_anything": 100,
    "test_malformed_poses_and_trajectories_are_refused_cleanly": 100,
    "test_bulk_config_mutations": 3000,
    "test_bulk_sweep_files": 2600,
    "test_corrupt_sweep_files_are_refused_cleanly": 300,
    "test_bulk_scene_arrays": 2000,
    "test_bulk_poses_and_trajectories": 1500,
    "test_hostile_but_valid_scenes_give_a_correct_result": 12,
    # through the command line (tests/addon/test_cli_hostile_input.py)
    "test_generated_command_lines_in_process": 200,
    "test_generated_command_lines_as_subprocesses": 3,
}
HOSTILE_TOTAL_FLOOR = 10_000

_counts: dict[str, int] = {}


@pytest.fixture
def hostile_attempts(request):
    """Call it once per attempt; the test's total is checked against its floor when the test ends."""
    name = request.node.originalname
    count = [0]

    def attempt(n: int = 1) -> int:
        count[0] += n
        return count[0]

    yield attempt
    _counts[request.node.nodeid] = count[0]
    floor = HOSTILE_FLOORS.get(name, 0)
    report = getattr(request.node, "rep_call", None)
    if report is None or report.passed:
        assert count[0] >= floor, f"{name}: {count[0]} attempts, fewer than its floor {floor}"


@pytest.fixture(scope="session")
def hostile_floors():
    return dict(HOSTILE_FLOORS), HOSTILE_TOTAL_FLOOR


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if rep.when == "call":
        item.rep_call = rep


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    base = _cpu_report_path()
    if base is not None and not os.environ.get("PYTEST_XDIST_WORKER") and base.parent.is_dir():
        terminalreporter.write_sep("-", f"CPU by test file ({CPU_REPORT_ENV}={base})")
        for line in cpu_report_lines(base):
            terminalreporter.write_line(line)
    if not _counts:
        return
    total = sum(_counts.values())
    names = {nodeid.split("::")[-1].split("[")[0] for nodeid in _counts}
    terminalreporter.write_line(f"hostile-input attempts: {total} in {len(_counts)} tests "
                                f"(floor of the whole suite {HOSTILE_TOTAL_FLOOR}; "
                                f"{'all' if set(HOSTILE_FLOORS) <= names else 'not all'} of its tests ran)")


def pytest_sessionfinish(session, exitstatus):
    names = {nodeid.split("::")[-1].split("[")[0] for nodeid in _counts}
    if _counts and set(HOSTILE_FLOORS) <= names and sum(_counts.values()) < HOSTILE_TOTAL_FLOOR:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED

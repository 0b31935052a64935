"""The hostile-input suite's attempt count (issue 31: at least 10,000 generated attempts, counted).

A test of the suite takes the ``hostile_attempts`` fixture and calls it once per attempt it makes (an input
generated, tried, and its outcome checked).  :data:`HOSTILE_FLOORS` holds the fewest attempts each such test
must make (checked when the test ends); their sum is at least :data:`HOSTILE_TOTAL_FLOOR`
(tests/core/test_fuzz_inputs.py checks).  The session's total is printed at the end of the test output, and a
session that ran every test of the suite with fewer attempts in all fails."""
from __future__ import annotations

import pytest

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

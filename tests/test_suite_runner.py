"""scripts/test.sh and tests/conftest.py: how the whole suite is run (two pytest-xdist workers, whole files, the
slowest first, a per-checkout kernel cache)."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("suite_conftest", REPO / "tests" / "conftest.py")
suite = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(suite)


@pytest.mark.parametrize("value", ["two", "-1", "1.5", "65"])
def test_a_bad_worker_count_is_one_line_before_any_setup(value):
    env = dict(os.environ, LADAR_TEST_WORKERS=value)
    proc = subprocess.run(["bash", "scripts/test.sh", "--collect-only"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"LADAR_TEST_WORKERS = '{value}'" in lines[0] and "0 (one process) to 64" in lines[0]
    assert "setup:" not in proc.stdout  # refused before setting anything up


def test_the_script_runs_pytest_on_workers_with_whole_files():
    text = (REPO / "scripts" / "test.sh").read_text(encoding="utf-8")
    assert '-n "$workers" --dist loadfile --no-loadscope-reorder "$@"' in text
    pins = (REPO / "requirements.txt").read_text(encoding="utf-8").splitlines()
    assert "pytest-xdist==3.8.0" in pins and "execnet==2.1.2" in pins


def test_every_listed_slow_file_exists():
    """A renamed or removed file must leave the table (it would silently count as quick otherwise)."""
    missing = [f for f in suite.SLOW_FILES if not (REPO / f).is_file()]
    assert not missing, missing


def _item(nodeid):
    return types.SimpleNamespace(nodeid=nodeid)


def test_workers_get_the_slowest_files_first_and_each_file_keeps_its_order(monkeypatch):
    slow, slower = sorted(suite.SLOW_FILES, key=suite.SLOW_FILES.get)[:2]
    items = [_item("tests/a_quick.py::t1"), _item(f"{slow}::x"), _item("tests/a_quick.py::t2"),
             _item(f"{slower}::b"), _item(f"{slower}::a"), _item("tests/z_quick.py::t")]
    order = [i.nodeid for i in items]
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    suite.pytest_collection_modifyitems(None, None, items)
    assert [i.nodeid for i in items] == order  # a serial run keeps pytest's order
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw0")
    suite.pytest_collection_modifyitems(None, None, items)
    assert [i.nodeid for i in items] == [f"{slower}::b", f"{slower}::a", f"{slow}::x", "tests/a_quick.py::t1",
                                         "tests/a_quick.py::t2", "tests/z_quick.py::t"]


def test_the_suite_keeps_its_kernels_in_this_checkout():
    """Set before any test imports the core (unless the caller chose a folder); subprocesses inherit it."""
    assert os.environ["LADAR_KERNEL_CACHE"]
    if os.environ["LADAR_KERNEL_CACHE"] == str(REPO / "build" / "kernel-cache"):
        import core.jit

        assert core.jit.CACHE_DIR.parent == REPO / "build" / "kernel-cache"
        ignored = subprocess.run(["git", "check-ignore", "-q", "build/kernel-cache/x"], cwd=REPO)
        assert ignored.returncode == 0, "build/ must be git-ignored"


def test_the_session_wrote_the_projects_bytecode():
    """tests/conftest.py compiles the project's modules once a session (fresh processes then read bytecode even
    where PYTHONDONTWRITEBYTECODE is set); a stale or missing file is written again."""
    import importlib.util

    for name in suite.BYTECODE_DIRS:
        source = next((REPO / name).rglob("*.py"))
        cached = Path(importlib.util.cache_from_source(str(source)))
        assert cached.is_file() and cached.stat().st_mtime >= source.stat().st_mtime - 1.0, cached
    cached = Path(importlib.util.cache_from_source(str(REPO / "core" / "jit.py")))
    cached.unlink()
    suite.compile_project()
    assert cached.is_file()


def test_the_first_files_go_before_the_slowest(monkeypatch):
    """tests/addon/test_cli.py (its warm-up fills an empty kernel cache for the session's ladar_run.py runs) is
    handed out first, ahead of files with larger figures; the others keep the longest-first order."""
    first = suite.FIRST_FILES[0]
    assert (REPO / first).is_file()
    heaviest = max((f for f in suite.SLOW_FILES if f not in suite.FIRST_FILES), key=suite.SLOW_FILES.get)
    assert suite.SLOW_FILES[heaviest] > suite.SLOW_FILES.get(first, 0.0)  # (else the test shows nothing)
    items = [_item("tests/a_quick.py::t"), _item(f"{heaviest}::x"), _item(f"{first}::w"), _item(f"{first}::v")]
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw0")
    suite.pytest_collection_modifyitems(None, None, items)
    assert [i.nodeid for i in items] == [f"{first}::w", f"{first}::v", f"{heaviest}::x", "tests/a_quick.py::t"]


_BUSY = "import time\nt = time.process_time()\nwhile time.process_time() - t < {s}:\n    pass\n"


def test_the_cpu_report_counts_each_tests_cpu_its_childrens_and_the_processes_it_started(tmp_path):
    """``LADAR_TEST_CPU_REPORT=FILE`` (tests/conftest.py): a session of two tests, one that burns 0.4 s of CPU
    in a child process it waits for and one that burns 0.3 s itself, run with the suite's conftest.  Each busy
    loop stops once its process's CPU clock has advanced by its figure, so the recorded CPU is at least that
    (the clocks tick in 1/100 s, hence the 0.02 s margin) and at most that plus the process's start-up and the
    test's own bookkeeping (< 1 s: a bare interpreter starts in 0.02 s of CPU)."""
    (tmp_path / "conftest.py").write_text("from tests.conftest import *  # noqa: F401,F403\n", encoding="utf-8")
    (tmp_path / "test_busy.py").write_text(
        "import subprocess, sys\n\n\ndef test_child():\n"
        f"    subprocess.run([sys.executable, '-c', {_BUSY.format(s=0.4)!r}], check=True)\n\n\n"
        "def test_self():\n" + "".join("    " + line + "\n" for line in _BUSY.format(s=0.3).splitlines()),
        encoding="utf-8")
    report = tmp_path / "cpu.jsonl"
    report.write_text('{"test": "an earlier session"}\n', encoding="utf-8")  # replaced, not appended to
    env = dict(os.environ, LADAR_TEST_CPU_REPORT=str(report), PYTHONPATH=str(REPO))
    env.pop("PYTEST_XDIST_WORKER", None)
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
                           "--rootdir", str(tmp_path), str(tmp_path / "test_busy.py")], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rows = {r["test"].rsplit("::", 1)[-1]: r for r in map(json.loads, report.read_text().splitlines())}
    assert sorted(rows) == ["test_child", "test_self"]
    child, own = rows["test_child"], rows["test_self"]
    assert 0.4 - 0.02 <= child["children_cpu_s"] < 0.4 + 1.0, child
    assert len(child["processes"]) == 1 and "process_time" in child["processes"][0], child
    assert 0.3 - 0.02 <= own["cpu_s"] < 0.3 + 1.0 and own["children_cpu_s"] < 0.02 and own["processes"] == [], own
    assert all(r["wall_s"] > 0 for r in rows.values())
    summary = [line for line in proc.stdout.splitlines() if "processes started" in line]
    assert len(summary) == 2 and summary[0].endswith("test_busy.py") and "1 processes started" in summary[0]
    assert summary[1].endswith("in all (1 files)"), summary
    lines = suite.cpu_report_lines(report)  # the same figures, summed by file
    total = (child["cpu_s"] + own["cpu_s"]) + (child["children_cpu_s"] + own["children_cpu_s"])  # (its order)
    assert lines[0].startswith(f"{total:7.1f} s CPU"), (lines, total)

"""A sweep on a real Dask cluster, the recipe of docs/sweeps.md ("On a cluster"), step for step: a separately
started ``dask scheduler`` and two ``dask worker`` processes (loopback 127.0.0.1 only, free ports picked at random,
no dashboards), then ``scripts/ladar_run.py … sweep docs/examples/cluster_small.toml --scheduler tcp://…``.  Every
point's result (the results table and each run's point cloud) must equal, bit for bit, the same sweep on the
default local cluster; a second sweep has one worker process killed (SIGKILL) while it holds a task, and must
still give every point once, done and equal.

The cluster's environment is this project's ``.venv`` with the project *not importable*: the scheduler and the
workers run ``.venv/bin/dask`` in an empty temporary folder, without ``PYTHONPATH`` or ``NUMBA_CACHE_DIR`` (checked:
``import core`` fails there, and neither the scheduler nor a worker can find ``core``).  A venv built from
requirements-worker.txt would be closer to a user's, but building one downloads about 150 MB of wheels (numba,
llvmlite, scipy, embreex, …; no pip cache here) on every fresh machine: minutes, and a network dependency for a
test.  What the venv adds — that requirements-worker.txt is complete — is checked by
tests/core/sweep/test_sweep_requirements.py (the list is closed under dependencies and covers every import of the
core); what this test checks is that nothing of the project is needed on the cluster: the client ships the core.

Every process is started in its own session and stopped (SIGTERM, then SIGKILL after 10 s) when the module's tests
end, passed or failed; the workers also exit by themselves 60 s after losing the scheduler (``--death-timeout``).
Each command has a timeout.  The first sweep on the cluster compiles the numba kernels in both workers (the shipped
core is a new path for numba's cache): about 2 minutes on a loaded 2-core machine; later tasks take ~0.1 s.
"""
from __future__ import annotations

import csv
import importlib.util
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parents[2]
SWEEP = REPO / "docs" / "examples" / "cluster_small.toml"
BLEND = REPO / "sample_blends" / "flash_demo.blend"
DASK = Path(sys.executable).parent / "dask"
N_TASKS = 12  # 4 ranges × 3 seeds (docs/examples/cluster_small.toml)
#: A cold sweep compiles the kernels in every worker process at once.
SWEEP_TIMEOUT_S = 900


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _clean_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    return env


def _stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + 10.0
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
        try:  # the whole session: a nanny's worker process too
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        p.wait(timeout=10)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """(scheduler address, the folder the cluster runs in): a scheduler and two single-threaded workers."""
    where = tmp_path_factory.mktemp("cluster")
    env = _clean_env()
    check = subprocess.run([sys.executable, "-c", "import core"], cwd=where, env=env, capture_output=True, text=True,
                           timeout=60)
    assert check.returncode != 0 and "No module named 'core'" in check.stderr  # the project is not importable
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = []
    logs = []
    try:
        log = open(where / "scheduler.log", "wb")
        logs.append(log)
        procs.append(subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                       "--no-dashboard"], cwd=where, env=env, stdout=log,
                                      stderr=subprocess.STDOUT, start_new_session=True))
        for i in range(2):
            log = open(where / f"worker{i}.log", "wb")
            logs.append(log)
            procs.append(subprocess.Popen([str(DASK), "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                                           "--no-dashboard", "--death-timeout", "60",
                                           "--local-directory", str(where / f"worker{i}")],
                                          cwd=where, env=env, stdout=log, stderr=subprocess.STDOUT,
                                          start_new_session=True))
        with distributed.Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            # neither the scheduler nor a worker has the project
            assert client.run_on_scheduler(importlib.util.find_spec, "core") is None
            assert list(client.run(importlib.util.find_spec, "core").values()) == [None, None]
        yield address, where
    finally:
        _stop(procs)
        for log in logs:
            log.close()


def _sweep_command(out, *options):
    return [sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(BLEND), "sweep", str(SWEEP), "--out",
            str(out), *options]


def _rows(folder: Path) -> dict:
    with open(folder / "results.csv", newline="", encoding="utf-8") as f:
        return {r["task"]: r for r in csv.DictReader(f)}


def _assert_same_results(folder: Path, reference: Path) -> None:
    """Every task done once, with the reference's table row (all but its run time) and point cloud, bit for bit."""
    rows, ref = _rows(folder), _rows(reference)
    assert len(rows) == len(ref) == N_TASKS and sorted(rows) == sorted(ref)
    for name, r in ref.items():
        got = rows[name]
        assert got["status"] == r["status"] == "done", (name, got["error"])
        assert {k: v for k, v in got.items() if k != "run_time_s"} == {k: v for k, v in r.items()
                                                                       if k != "run_time_s"}
        with np.load(folder / got["run"] / "points.npz") as a, np.load(reference / r["run"] / "points.npz") as b:
            assert sorted(a.files) == sorted(b.files)
            for key in b.files:
                assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key], equal_nan=a[key].dtype.kind
                                                                       == "f"), (name, key)
    # one run folder per task, nothing else (no staging folder left by a killed worker, no failure record)
    assert sorted(p.name for p in (folder / "runs").iterdir()) == sorted(rows)
    assert not (folder / "failed").exists() or not any((folder / "failed").iterdir())


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "sweep"
    t0 = time.perf_counter()
    res = subprocess.run(_sweep_command(out, "--workers", "2"), capture_output=True, text=True,
                         timeout=SWEEP_TIMEOUT_S)
    print(f"local cluster sweep: {time.perf_counter() - t0:.1f} s")
    assert res.returncode == 0, res.stderr
    assert f"tasks    {N_TASKS}/{N_TASKS} done, 0 failed" in res.stdout
    return out


def test_sweep_on_a_separately_started_scheduler_equals_the_local_cluster(cluster, local_sweep, tmp_path):
    address, where = cluster
    out = tmp_path / "remote"
    t0 = time.perf_counter()
    res = subprocess.run(_sweep_command(out, "--scheduler", address), capture_output=True, text=True,
                         timeout=SWEEP_TIMEOUT_S)
    print(f"remote sweep: {time.perf_counter() - t0:.1f} s")
    assert res.returncode == 0, res.stderr + (where / "scheduler.log").read_text(errors="replace")[-3000:]
    assert f"tasks    {N_TASKS}/{N_TASKS} done, 0 failed; {N_TASKS} run now on 2 worker(s)" in res.stdout
    assert "Traceback" not in res.stderr
    _assert_same_results(out, local_sweep)
    # the scheduler never had to unpickle the core (issue 26: "No module named 'ladar_core_…'")
    log = (where / "scheduler.log").read_text(errors="replace")
    assert "ModuleNotFoundError" not in log and "Error during deserialization" not in log


def test_a_worker_killed_mid_sweep_loses_nothing_and_repeats_nothing(cluster, local_sweep, tmp_path):
    address, where = cluster
    out = tmp_path / "killed"
    log = open(tmp_path / "cli.log", "w+")
    proc = subprocess.Popen(_sweep_command(out, "--scheduler", address), stdout=log, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    killed = None
    try:
        with distributed.Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            deadline = time.monotonic() + SWEEP_TIMEOUT_S
            while proc.poll() is None and time.monotonic() < deadline:
                runs = out / "runs"
                done = [p for p in runs.iterdir() if not p.name.startswith(".")] if runs.is_dir() else []
                if killed is None and done:  # at least one task finished: kill a worker holding another
                    busy = {w: keys for w, keys in client.processing().items() if keys}
                    if busy:
                        worker = sorted(busy)[0]
                        pid = client.run(os.getpid, workers=[worker])[worker]
                        os.kill(pid, signal.SIGKILL)
                        killed = (worker, list(busy[worker]), len(done))
                time.sleep(0.02)
            proc.wait(timeout=max(1.0, deadline - time.monotonic()))
            client.wait_for_workers(2, timeout=120)  # the nanny restarted the killed worker process
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        log.seek(0)
        text = log.read()
        log.close()
    assert killed is not None, "no worker held a task after the first finished"
    assert killed[2] < N_TASKS
    assert proc.returncode == 0, text
    assert f"tasks    {N_TASKS}/{N_TASKS} done, 0 failed" in text and "Traceback" not in text
    _assert_same_results(out, local_sweep)

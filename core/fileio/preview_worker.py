"""PNG previews drawn by worker processes, off a headless command's critical path (issue 25).

A command that will draw previews (``simulate`` without ``--no-previews``) starts a worker process first thing
(:meth:`PreviewPool.start`: ``scripts/ladar_run.py`` before Blender loads, ``blender -c ladar`` before the
simulator's imports).  The worker imports matplotlib and :mod:`core.fileio.preview` while the command starts
Blender and runs the frame (on the other core), then waits.  When the run's products are in its staging folder
the command hands the folder(s) over (:meth:`PreviewPool.draw`) and the worker draws them in ``drawers``
processes at once (default: 2 where there are 2 cores or more): itself and copies of itself made with
``os.fork`` (each already has matplotlib loaded: a second worker process would import it again, 0.9 s of CPU
taken from the command's start).  Drawer ``j`` of ``d`` draws every ``d``-th preview from the ``j``-th
(``write_run_previews(..., share=(j, d))``), reading the arrays from disk like an in-process draw, each PNG
written atomically into the staging folder; the command commits the folder only after the worker has finished.
The PNGs are byte for byte those of one in-process draw (each slice is the same PNG whether drawn in full or
replayed: :class:`core.fileio.preview.FigureReplay`).

A forked drawer that dies leaves its share to its worker (after removing what it left half-written).  A worker
that cannot start, dies, stops answering or reports an error costs one ``note`` line: the command draws that
worker's share itself (files the worker finished are complete and left alone; a temporary file it left
half-written is removed first).  Cancel (``cancel()`` true, Ctrl-C, SIGTERM, SIGHUP: an exception in the
waiting thread) kills the workers and waits for them before the exception goes on, so the staging folder's
removal cannot race a worker's write.  No worker outlives its command: each reads its orders from a pipe and
exits when it closes (the command's exit), on Linux it also gets SIGKILL when the thread that started it ends
(``PR_SET_PDEATHSIG``: a killed command), and it ignores SIGINT and SIGHUP (the command decides: a terminal's
Ctrl-C reaches the whole process group).

The worker runs the command's own interpreter (``sys.executable``: the venv's Python under the ``bpy`` module,
Blender's bundled Python in Blender) with ``-I -S`` and the command's ``sys.path`` (so the extension's bundled
wheels are found), importing the core under the name ``core`` from the folder that holds this package.  Where
``sys.executable`` is not a Python (an embedding program reporting itself), or off POSIX (the command waits on
the worker's pipe with ``selectors``), no worker starts and the previews are drawn in process.
By default a worker starts only where a core is idle when the command starts (:func:`idle_cores`: on a busy
machine its imports would take CPU from the command's own start and cost more than they save), and forks its
second drawer only where one is idle when it draws.  ``LADAR_PREVIEW_WORKERS`` decides instead: the number of
processes that draw at once (1: one worker that does not fork; 0: no worker, the previews are drawn in process).

The command's side; the worker's is :mod:`core.fileio.preview_serve`.  Standard library only (``scripts/ladar_run.py``
imports this module before Blender starts).
"""
from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

from ..errors import Cancelled

#: Processes that draw at once (``LADAR_PREVIEW_WORKERS`` overrides; 0: previews drawn in process).
DEFAULT_DRAWERS = 2
#: A worker that has said nothing for this long while drawing is taken as hung: killed, its share drawn here.
SILENCE_TIMEOUT_S = 120.0
#: How long :meth:`PreviewPool.close` waits for an idle worker to exit on its pipe's end before killing it.
CLOSE_WAIT_S = 2.0
POLL_S = 0.05

#: The worker's first lines (``python -I -S -c BOOTSTRAP``): the settings arrive on stdin as one JSON line.
BOOTSTRAP = ("import sys, json\n"
             "cfg = json.loads(sys.stdin.readline())\n"
             "sys.path[:] = cfg['path']\n"
             "sys.dont_write_bytecode = cfg['dont_write_bytecode']\n"
             "import core.fileio.preview_serve as w\n"
             "w.serve(cfg)\n")


def worker_count() -> int | None:
    """``LADAR_PREVIEW_WORKERS``: how many processes draw a command's previews at once (0: none, the command draws
    them; at most 8); None where it is not set (:func:`idle_cores` decides)."""
    text = os.environ.get("LADAR_PREVIEW_WORKERS", "").strip()
    if not text:
        return None
    try:
        n = int(text)
    except ValueError:
        return None
    return max(0, min(n, 8))


def idle_cores() -> float:
    """Cores no process wants now: the CPU count less the runnable tasks (``/proc/loadavg``'s instantaneous count,
    the caller included; elsewhere the 1-minute load average and the caller).  A worker only pays where a core
    would otherwise idle: measured on 2 cores with 3–5 other runnable jobs, its imports (≈ 1.2 s of CPU, 0.7 s
    more than drawing in the command) slowed the flash demo's and the profiler's whole command by 0.7–1.1 s while
    its previews' wait shrank by 0.6–0.7 s (docs/performance.md)."""
    cpus = os.cpu_count() or 1
    try:
        with open("/proc/loadavg", encoding="ascii") as f:
            running = int(f.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        try:
            running = os.getloadavg()[0] + 1.0
        except (OSError, AttributeError):
            return 0.0
    return float(cpus - running)


def default_drawers() -> int:
    """Processes drawing at once when ``LADAR_PREVIEW_WORKERS`` is not set: :data:`DEFAULT_DRAWERS` (at most the
    CPU count) where a core is idle now, else 0 (the command draws its previews itself)."""
    if idle_cores() < 1.0:
        return 0
    return max(1, min(DEFAULT_DRAWERS, os.cpu_count() or 1))


def python_executable() -> str | None:
    """The interpreter a worker runs (``sys.executable``), or None where it is not a Python."""
    exe = sys.executable
    if os.name != "posix" or not exe or not os.path.isfile(exe):
        return None
    name = os.path.basename(exe).lower()
    if not name.startswith(("python", "pypy")):  # e.g. an embedding program reporting itself
        return None
    return exe


def _core_root() -> str:
    """The folder holding this ``core`` package (a checkout, or the installed extension's folder)."""
    return str(Path(__file__).absolute().parents[2])


class _Worker:
    """One worker process, seen from the command."""

    def __init__(self, proc: subprocess.Popen):
        self.proc = proc
        self.buffer = b""
        self.failed = None        # why it stopped, once it has
        self.drawers = {}         # drawer index -> process id, as reported while drawing

    @property
    def pid(self) -> int:
        return self.proc.pid

    def send(self, message: dict) -> None:
        self.proc.stdin.write((json.dumps(message) + "\n").encode("utf-8"))
        self.proc.stdin.flush()

    def kill(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.kill()
            except OSError:  # pragma: no cover - already gone
                pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:  # pragma: no cover - a process SIGKILL does not end
            pass
        self._close_pipes()

    def close(self) -> None:
        """End an idle worker: its pipe closes, it exits; killed if it does not within CLOSE_WAIT_S."""
        if self.proc.poll() is None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
            try:
                self.proc.wait(timeout=CLOSE_WAIT_S)
            except subprocess.TimeoutExpired:
                pass
        self.kill()

    def _close_pipes(self) -> None:
        for pipe in (self.proc.stdin, self.proc.stdout):
            try:
                if pipe is not None:
                    pipe.close()
            except OSError:
                pass


class PreviewPool:
    """The preview workers of one command (see the module's text).  ``start`` never raises: a pool whose workers
    could not start has none, and :meth:`draw` then leaves every preview to the caller."""

    def __init__(self, workers=()):
        self.workers = list(workers)
        self.notes = []

    @classmethod
    def start(cls, drawers: int | None = None) -> "PreviewPool":
        """``drawers``: processes drawing at once per worker (0: no worker).  Default: ``LADAR_PREVIEW_WORKERS``,
        else :func:`default_drawers`, and then the worker forks its second drawer only if a core is idle when it
        draws (``adaptive``)."""
        adaptive = drawers is None and worker_count() is None
        if drawers is None:
            drawers = default_drawers() if adaptive else worker_count()
        drawers = int(drawers)
        exe = python_executable()
        pool = cls()
        if drawers <= 0 or exe is None:
            return pool
        cfg = json.dumps({"path": [_core_root()] + [p for p in sys.path if p], "parent": os.getpid(),
                          "drawers": drawers, "adaptive": adaptive,
                          "dont_write_bytecode": bool(sys.dont_write_bytecode)}) + "\n"
        try:
            proc = subprocess.Popen([exe, "-I", "-S", "-c", BOOTSTRAP], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, close_fds=True,
                                    cwd=os.getcwd())
        except (OSError, ValueError) as exc:
            pool.notes.append(f"no preview worker ({exc}); the previews are drawn here")
            return pool
        worker = _Worker(proc)
        pool.workers.append(worker)
        try:
            proc.stdin.write(cfg.encode("utf-8"))
            proc.stdin.flush()
        except OSError as exc:
            worker.failed = f"it did not start ({exc})"
        return pool

    @property
    def pids(self) -> list[int]:
        return [w.pid for w in self.workers]

    def live(self) -> list[_Worker]:
        return [w for w in self.workers if w.failed is None and w.proc.poll() is None]

    def draw(self, folders, *, cancel=None, progress=None, note=None) -> list[tuple[Path, tuple[int, int]]]:
        """Have the live workers draw the previews of ``folders`` (run folders still being assembled), each
        worker its share.  Returns the (folder, share) pairs the caller must draw itself (those of a worker that
        failed; every share when no worker is live), after removing what a failed worker left half-written.

        ``progress(index, done)``: folder ``index``'s previews drawn so far by all workers (out of
        :func:`core.fileio.preview.preview_count`).  ``cancel()`` true raises Cancelled; it, or any exception here
        (a signal), kills every worker and waits for it before going on."""
        folders = [Path(f).absolute() for f in folders]
        live = self.live()
        n = len(live)
        if n == 0:
            stopped = [w for w in self.workers if w.failed is None]
            for w in stopped:  # (died while loading, e.g. a package missing from its Python)
                w.failed = f"it exited (code {w.proc.wait()}) before drawing"
            if note is not None and self.workers:
                note(f"no preview worker is running ({(stopped or self.workers)[0].failed}); the previews are drawn "
                     "here")
            return [(f, (0, 1)) for f in folders]
        done = {}  # (worker index, drawer index, folder index) -> previews that drawer has done
        pending = {}
        selector = selectors.DefaultSelector()
        try:
            for k, w in enumerate(live):
                try:
                    w.send({"folders": [str(f) for f in folders], "share": [k, n]})
                except OSError as exc:
                    w.failed = f"it had stopped ({exc})"
                    continue
                pending[k] = time.monotonic()
                selector.register(w.proc.stdout, selectors.EVENT_READ, k)
            while pending:
                if cancel is not None and cancel():
                    raise Cancelled()
                for key, _ in selector.select(POLL_S):
                    k = key.data
                    w = live[k]
                    chunk = os.read(w.proc.stdout.fileno(), 65536)
                    if not chunk:
                        w.failed = f"it exited (code {w.proc.wait()})"
                    w.buffer += chunk
                    while b"\n" in w.buffer and w.failed is None:
                        line, w.buffer = w.buffer.split(b"\n", 1)
                        pending[k] = time.monotonic()
                        word, _, rest = line.decode("utf-8", "replace").partition(" ")
                        if word == "progress":
                            fi, d, j, pid = (int(x) for x in rest.split()[:4])
                            done[k, j, fi] = d
                            w.drawers[j] = pid
                            if progress is not None:
                                progress(fi, sum(v for (_, _, f), v in done.items() if f == fi))
                        elif word == "done":
                            pending.pop(k, None)
                            selector.unregister(w.proc.stdout)
                            break
                        elif word == "error":
                            w.failed = f"it failed: {rest}"
                    if w.failed is not None and k in pending:
                        pending.pop(k)
                        selector.unregister(w.proc.stdout)
                now = time.monotonic()
                for k, last in list(pending.items()):
                    if now - last > SILENCE_TIMEOUT_S:
                        live[k].failed = f"it said nothing for {SILENCE_TIMEOUT_S:.0f} s"
                        pending.pop(k)
                        selector.unregister(live[k].proc.stdout)
        except BaseException:
            self.kill()
            raise
        finally:
            selector.close()
        todo = []
        for k, w in enumerate(live):
            if w.failed is None:
                continue
            w.kill()  # (a failed worker is ended before its leftovers are removed)
            for f in folders:
                remove_partial_pngs(f)
            todo += [(f, (k, n)) for f in folders]
            if note is not None:
                note(f"preview worker {k + 1} of {n} stopped ({w.failed}); its previews are drawn here")
        return todo

    def kill(self) -> None:
        """Kill every worker and wait for it (cancel, or the command's end without :meth:`close`)."""
        for w in self.workers:
            w.kill()

    def close(self) -> None:
        """End the workers (idle ones exit when their pipe closes)."""
        for w in self.workers:
            if w.proc.poll() is None:
                try:
                    w.proc.stdin.close()
                except OSError:
                    pass
        deadline = time.monotonic() + CLOSE_WAIT_S
        for w in self.workers:
            try:
                w.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
            w.kill()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def remove_partial_pngs(folder) -> list[Path]:
    """The hidden temporary files of PNGs a killed writer left in ``folder`` (and its ``slices/``):
    ``.<name>.png.<random>.tmp`` (core.fileio.staging.write_file_atomically).  Returns the removed paths."""
    removed = []
    for sub in (Path(folder), Path(folder) / "slices"):
        if not sub.is_dir():
            continue
        for tmp in sub.glob(".*.png.*.tmp"):
            try:
                tmp.unlink()
                removed.append(tmp)
            except FileNotFoundError:
                pass
    return removed

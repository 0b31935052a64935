"""The process's one pool of worker threads, shared by every parallel stage (frame blocks, receiver chain,
echo detection, false-alarm classification, extinction bands).

A frame used to start a pool of its own for each of these stages (six to eight per noisy flash frame), and a
new thread must be scheduled before ``Thread.start`` returns: ≈ 0.1 ms each on an idle machine, milliseconds
when the cores are busy (the frame's own other thread among them).  The pool here is started once per process
and grows to the largest thread count asked for; a call runs on at most ``threads`` threads.

:func:`map_list` runs the items on the calling thread and ``threads`` − 1 workers, in stretches of consecutive
items with work taken from the longest stretch left (the stages that fill a fresh output); :func:`imap` runs them
on ``threads`` workers and yields the results in item order while the caller reports progress (the frame
blocks).  In both the first error (by item) is raised after the running items have finished, so a caller never
returns while its items still write to its arrays — except for a signal (KeyboardInterrupt, core.process's
Interrupted, which wins over any item's error): the process is ending, and a worker in the middle of a kernel's
compile (up to ≈ 30 s on a first run) is not waited for; the command line then exits without joining the pool
(scripts/ladar_run.py).  Called from one of the pool's own workers (a stage inside a
stage) either runs the items in that thread, one after the other: a worker never waits for the pool it belongs
to.  A forked child process starts a pool of its own.  Results never depend on the thread count (each caller's
items are independent).
"""
from __future__ import annotations

import itertools
import os
import queue
import threading
from concurrent.futures import ThreadPoolExecutor

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_pid = 0
_local = threading.local()


def _mark_worker() -> None:
    _local.worker = True


def _executor(threads: int) -> ThreadPoolExecutor:
    """The shared pool, with at least ``threads`` workers.  A call that needs more replaces it; the old one is not
    shut down (a concurrent call may still be submitting to it): its workers end once nothing refers to it."""
    global _pool, _pool_size, _pool_pid
    with _lock:
        if _pool is None or _pool_size < threads or _pool_pid != os.getpid():
            _pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="ladar-worker",
                                       initializer=_mark_worker)
            _pool_size, _pool_pid = threads, os.getpid()
        return _pool


def in_worker() -> bool:
    """True in one of the shared pool's worker threads."""
    return getattr(_local, "worker", False)


def imap(fn, items, threads: int):
    """``fn(item)`` for every item, on up to ``threads`` of the shared pool's workers; yields the results in
    item order as they are ready.  One thread, one item, or a call from a worker: the items run in the calling
    thread."""
    items = list(items)
    n = len(items)
    k = min(int(threads), n)
    if k <= 1 or in_worker():
        for item in items:
            yield fn(item)
        return
    results = [None] * n
    done = [False] * n
    errors: dict[int, BaseException] = {}
    lock = threading.Lock()
    stop = threading.Event()
    order = itertools.count()
    # The caller waits on SimpleQueues, never on a threading.Condition: a signal's exception (core.process raises
    # Interrupted in the main thread) raised inside Condition.wait between its release of the lock and its
    # try-block leaves the lock released, and the `with` block's exit then fails ("RuntimeError: cannot release
    # un-acquired lock", exit 1 instead of the signal's); SimpleQueue.get is one C call that the handler's
    # exception leaves cleanly.  ``ready``: an item's index once its result is in, -1 once a runner stopped on an
    # error; ``ended``: one token per runner that has returned.
    ready: queue.SimpleQueue = queue.SimpleQueue()
    ended: queue.SimpleQueue = queue.SimpleQueue()

    def runner():
        try:
            while not stop.is_set():
                with lock:
                    i = next(order)
                if i >= n:
                    return
                try:
                    value = fn(items[i])
                except BaseException as exc:  # noqa: BLE001 - handed to the caller
                    with lock:
                        errors[i] = exc
                    stop.set()
                    ready.put(-1)
                    return
                results[i] = value
                done[i] = True
                ready.put(i)
        finally:
            ended.put(None)

    pool = _executor(k)
    futures = [pool.submit(runner) for _ in range(k)]
    finished = interrupted = False
    try:
        for i in range(n):
            while not done[i] and not errors:
                ready.get()
            if not done[i]:
                break
            value, results[i] = results[i], None
            yield value
        else:
            finished = True
    except KeyboardInterrupt:  # a signal (core.process): the process is ending, its items are not waited for
        interrupted = True
        raise
    finally:
        stop.set()
        if not interrupted:
            for _ in futures:  # the running items finish before the caller goes on (or unwinds)
                ended.get()
    if not finished and errors:
        raise _first(errors)


def map_list(fn, items, threads: int) -> list:
    """``[fn(item) for item in items]`` on the calling thread and up to ``threads`` − 1 of the shared pool's
    workers.  Each thread starts at the front of its own stretch of consecutive items (the caller: the first) and,
    once that is done, takes items from the back of the longest stretch left: every thread writes mostly its own
    part of a fresh output (its pages' first touches), and a thread the system runs less leaves its items to the
    others instead of holding up the end.  An error stops the other threads at their next item; the first one
    (by item) is raised once every running item has finished.  Called from a worker: the items run in order in
    that thread."""
    items = list(items)
    n = len(items)
    k = min(int(threads), n)
    if k <= 1 or in_worker():
        return [fn(item) for item in items]
    results = [None] * n
    spans = [[n * t // k, n * (t + 1) // k] for t in range(k)]
    lock = threading.Lock()
    errors: dict[int, BaseException] = {}

    def take(t):
        with lock:
            if errors:
                return -1
            s = spans[t]
            if s[0] < s[1]:
                s[0] += 1
                return s[0] - 1
            s = max(spans, key=lambda v: v[1] - v[0])
            if s[0] < s[1]:
                s[1] -= 1
                return s[1]
            return -1

    def run(t):
        while (i := take(t)) >= 0:
            try:
                results[i] = fn(items[i])
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                with lock:
                    errors[i] = exc
                return

    ended: queue.SimpleQueue = queue.SimpleQueue()  # one token per worker that has returned (imap: why not a Future)

    def worker(t):
        try:
            run(t)
        finally:
            ended.put(None)

    pool = _executor(k - 1)
    futures = [pool.submit(worker, t) for t in range(1, k)]
    interrupted = False
    try:
        run(0)
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        if not interrupted and not any(isinstance(e, KeyboardInterrupt) for e in list(errors.values())):
            for _ in futures:  # (a worker that has not started takes nothing: every item is done or stopped)
                ended.get()
    if errors:
        raise _first(errors)
    return results


def _first(errors: dict) -> BaseException:
    """The error to raise: a signal's (KeyboardInterrupt, core.process.Interrupted) before any item's, else the
    first item's."""
    for i in sorted(errors):
        if isinstance(errors[i], KeyboardInterrupt):
            return errors[i]
    return errors[min(errors)]

"""core/threads.py: the process's one worker pool — results in item order, at most ``threads`` items at once,
errors raised by item after the running items finished, nested calls run inline, the pool kept between calls;
map_list's stretches (each thread its own run of consecutive items first) and work taken from the longest."""
import os
import threading
import time

import pytest

from core import threads as th


@pytest.mark.parametrize("run", [th.map_list, lambda f, x, t: list(th.imap(f, x, t))], ids=["map_list", "imap"])
def test_results_come_in_item_order_on_the_requested_threads(run):
    lock = threading.Lock()
    state = {"now": 0, "most": 0, "names": set()}

    def work(x):
        with lock:
            state["now"] += 1
            state["most"] = max(state["most"], state["now"])
            state["names"].add(threading.current_thread().name)
        time.sleep(0.002 * (x % 3))  # finish out of order
        with lock:
            state["now"] -= 1
        return x * x

    assert run(work, range(40), 3) == [x * x for x in range(40)]
    assert state["most"] <= 3 and len(state["names"]) <= 3
    me = threading.current_thread().name
    assert all(name.startswith("ladar-worker") or name == me for name in state["names"])


def test_one_thread_or_one_item_runs_in_the_calling_thread():
    me = threading.current_thread().name
    assert th.map_list(lambda x: threading.current_thread().name, range(3), 1) == [me] * 3
    assert th.map_list(lambda x: threading.current_thread().name, [0], 8) == [me]
    assert th.map_list(lambda x: x, [], 4) == []


def test_the_pool_is_kept_between_calls():
    th.map_list(lambda x: x, range(8), 2)
    before = {t.ident for t in threading.enumerate()}
    for _ in range(20):
        th.map_list(lambda x: x, range(8), 2)
    assert {t.ident for t in threading.enumerate()} == before  # no thread started (nor ended) by the 20 calls


@pytest.mark.parametrize("run", [th.map_list, lambda f, x, t: list(th.imap(f, x, t))], ids=["map_list", "imap"])
def test_the_first_error_by_item_is_raised_after_the_running_items_finished(run):
    finished, started = [], []
    lock = threading.Lock()

    def work(x):
        with lock:
            started.append(x)
        if x == 5:
            raise ValueError("item 5")
        if x == 2:
            raise KeyError("item 2")
        time.sleep(0.01)
        with lock:
            finished.append(x)
        return x

    with pytest.raises(KeyError):
        run(work, range(200), 2)
    running = set(started) - set(finished) - {2, 5}
    assert running == set()  # every item that started had finished when the call raised
    assert len(started) < 200  # and no item started after the error was seen (but the ones running then)


def test_results_before_an_error_are_yielded_then_it_is_raised():
    def work(x):
        if x == 3:
            raise RuntimeError("three")
        return x

    got = []
    with pytest.raises(RuntimeError, match="three"):
        for v in th.imap(work, range(10), 2):
            got.append(v)
    assert got == [0, 1, 2]


def test_a_call_from_a_worker_runs_its_items_in_that_worker():
    def outer(x):
        here = threading.current_thread().name
        inner = th.map_list(lambda y: threading.current_thread().name, range(4), 2)
        return here, inner

    for here, inner in th.imap(outer, range(4), 2):  # (imap: every item on a worker)
        assert th.in_worker() is False
        assert here.startswith("ladar-worker")
        assert inner == [here] * 4  # no wait on the pool the worker belongs to: no deadlock
    for here, inner in th.map_list(outer, range(6), 3):  # items on the caller may use the pool, on workers not
        assert len(inner) == 4 and (not here.startswith("ladar-worker") or inner == [here] * 4)


def test_map_list_threads_start_with_their_own_stretch():
    """Three threads, 30 slow items: the caller's first item is item 0, each worker's first is the start of its
    stretch (10 or 20); every item runs once."""
    first, seen = {}, []
    lock = threading.Lock()

    def work(x):
        with lock:
            first.setdefault(threading.current_thread().name, x)
            seen.append(x)
        time.sleep(0.003)
        return x

    assert th.map_list(work, range(30), 3) == list(range(30))
    assert sorted(seen) == list(range(30))
    assert first[threading.current_thread().name] == 0
    assert sorted(v for k, v in first.items() if k != threading.current_thread().name) in ([10, 20], [10], [20], [])


def test_an_abandoned_iteration_waits_for_its_running_items():
    done = []

    def work(x):
        time.sleep(0.01)
        done.append(x)
        return x

    it = th.imap(work, range(50), 2)
    assert next(it) == 0
    it.close()  # the consumer stops early: the items still running finish, no new one starts
    n = len(done)
    time.sleep(0.05)
    assert len(done) == n < 50


@pytest.mark.skipif(not hasattr(os, "fork"), reason="POSIX fork")
def test_a_forked_child_starts_a_pool_of_its_own():
    th.map_list(lambda x: x, range(4), 2)  # the parent's pool exists
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: the parent's worker threads do not exist here
        try:
            ok = th.map_list(lambda x: x + 1, range(6), 2) == [1, 2, 3, 4, 5, 6]
            os.write(w, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(w)
    assert os.read(r, 1) == b"1"
    os.close(r)
    os.waitpid(pid, 0)


def test_map_list_from_concurrent_callers_and_more_threads_than_items():
    """map_list (the receiver chain's and the detection's work sharing): results in item order whatever the
    thread count, also with more threads than items, from concurrent callers, and an error in any item is
    raised."""
    in_parallel = th.map_list

    for threads in (1, 2, 3, 8):
        assert in_parallel(lambda x: (time.sleep(0.0005 * (x % 3)), x * x)[1], range(11), threads) == [
            x * x for x in range(11)]
    assert in_parallel(abs, [], 2) == [] and in_parallel(abs, [-5], 4) == [5]

    def bad(x):
        if x == 6:
            raise ValueError("item 6")
        time.sleep(0.001)
        return x

    with pytest.raises(ValueError, match="item 6"):
        in_parallel(bad, range(16), 2)

    def caller(k):
        for i in range(20):
            assert in_parallel(lambda x: x + k, range(9), 2 + (i + k) % 3) == [x + k for x in range(9)]

    assert _run_callers(caller, 3) == []


def test_callers_asking_for_more_threads_while_others_run():
    """A call that grows the pool while other calls are submitting to the old one: every call completes
    (the replaced pool is not shut down under them)."""
    held = th._executor(2)  # what a running call holds
    th._executor(64)  # another call grows the pool
    assert held.submit(lambda: 7).result() == 7  # the held pool still takes work

    def caller(k):
        for i in range(30):
            n = 2 + (k * 7 + i) % 6
            assert th.map_list(lambda x: x * k, range(12), n) == [x * k for x in range(12)]
            assert list(th.imap(lambda x: x + k, range(5), n)) == [x + k for x in range(5)]

    assert _run_callers(caller, 4) == []


def _run_callers(caller, n):
    """Run caller(0) … caller(n − 1) on n threads of their own at once; the errors they raised."""
    errors = []

    def guarded(k):
        try:
            caller(k)
        except Exception as exc:  # reported by the caller of this helper
            errors.append(exc)

    threads = [threading.Thread(target=guarded, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return errors


@pytest.mark.parametrize("run", [th.map_list, lambda f, x, t: list(th.imap(f, x, t))], ids=["map_list", "imap"])
def test_the_caller_never_waits_in_a_condition_a_signal_could_break(run, monkeypatch):
    """A signal's exception (core.process raises Interrupted in the main thread) raised inside CPython's
    Condition.wait after it released the lock and before its try-block left the lock released: the caller's
    ``with cond`` then failed with "RuntimeError: cannot release un-acquired lock" (exit 1 with a traceback instead
    of the signal's exit; seen once in test_fault_injection's SIGHUP during a cold compile).  Here every
    Condition.wait of the calling thread does exactly that (releases, then raises): the old imap (its
    ``cond.wait``) and map_list (``Future.result``) fail with a RuntimeError releasing the unheld lock; the caller
    now waits only on
    SimpleQueue.get, which a signal leaves cleanly, so the items' results come back as without the patch."""
    caller = threading.current_thread()
    real_wait = threading.Condition.wait

    def wait_then_signal(self, timeout=None):
        if threading.current_thread() is caller:
            self._release_save()  # the window: the lock released, the try-block not yet entered
            raise KeyboardInterrupt("a signal inside Condition.wait")
        return real_wait(self, timeout)

    def slow(x):
        time.sleep(0.01 * (x % 3))  # the caller must wait for its workers
        return 2 * x

    monkeypatch.setattr(threading.Condition, "wait", wait_then_signal)
    assert run(slow, range(12), 2) == [2 * x for x in range(12)]

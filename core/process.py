"""What a command-line process needs: signals handled like Ctrl-C, blocks they cannot cut, output that a closed
pipe cannot break.  Standard library only (``scripts/ladar_run.py`` imports it before Blender starts).

SIGINT, SIGTERM and SIGHUP end a command the way Ctrl-C does, and never in the middle of a rename.

A command line (``ladar`` / ``scripts/ladar_run.py``) runs inside :func:`interrupts_as_exceptions`: the first of
those signals raises :class:`Interrupted` (a ``KeyboardInterrupt``, so every ``except KeyboardInterrupt`` and
``finally`` clean-up runs: the hidden staging folder is removed, nothing of the run is left).  Batch schedulers
and ``timeout`` send SIGTERM, a closed terminal SIGHUP.  While the clean-up runs, further signals are ignored
for :data:`CLEANUP_GRACE_S` (one clean-up, not an interrupted one).  Code that must not be cut in two (creating
a claim, the renames that put a run in place, a kernel's compile or load: core.jit) runs in :func:`deferred`: a
signal arriving inside waits until the block ends.  SIGKILL cannot be caught: what a killed run leaves is recognised and removed by the next run
(core.fileio.staging).

Library code never installs handlers: without :func:`interrupts_as_exceptions` (Blender's interface, scripts)
:func:`deferred` does nothing.  Handlers live in the main thread only; elsewhere both are no-ops.

Output: progress and summaries go through :func:`emit`, which never raises.  When the reader has gone
(``ladar … | head -5``: EPIPE), that stream is silenced for the rest of the process and the run carries on: the
run folder is what matters, progress lines never cost it.  :func:`interrupts_as_exceptions` also ignores SIGPIPE
(Python does; an embedding program such as Blender may not), so a write to a closed pipe is an error, not death.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from contextlib import contextmanager

#: Signals handled like Ctrl-C (those the platform has).
SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))
#: After the first signal, later ones are ignored this long (the clean-up it started must finish).
CLEANUP_GRACE_S = 5.0


class Interrupted(KeyboardInterrupt):
    """A run ended by a signal (SIGINT, SIGTERM, SIGHUP).  ``exit_code`` is 128 + the signal number."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        super().__init__(signal.Signals(signum).name)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name


def exit_code(exc: BaseException) -> int:
    """The process exit code for an interruption: 128 + signal (130 for Ctrl-C)."""
    return exc.exit_code if isinstance(exc, Interrupted) else 128 + int(signal.SIGINT)


class _State:
    def __init__(self):
        self.installed = 0       # nesting depth of interrupts_as_exceptions
        self.defer = 0           # nesting depth of deferred() (main thread)
        self.pending = None      # a signal that arrived inside deferred()
        self.fired_at = None     # when Interrupted was raised


_state = _State()


def _on_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _handler(signum, frame):
    if _state.fired_at is not None and time.monotonic() - _state.fired_at < CLEANUP_GRACE_S:
        return  # the clean-up of the first signal is running
    if _state.defer > 0:
        _state.pending = signum
        return
    _state.fired_at = time.monotonic()
    raise Interrupted(signum)


@contextmanager
def interrupts_as_exceptions(signals=SIGNALS):
    """Within the block, SIGINT/SIGTERM/SIGHUP raise :class:`Interrupted`; the previous handlers come back after.

    A signal that arrived inside :func:`deferred` at the block's end, or one raised meanwhile, is reported by
    :func:`pending_signal`."""
    if not _on_main_thread():
        yield
        return
    previous = {}
    for sig in tuple(signals) + ((signal.SIGPIPE,) if hasattr(signal, "SIGPIPE") else ()):
        try:
            previous[sig] = signal.signal(sig, signal.SIG_IGN if sig == getattr(signal, "SIGPIPE", None)
                                          else _handler)
        except (OSError, ValueError):  # pragma: no cover - not settable here
            pass
    _state.installed += 1
    if _state.installed == 1:
        _state.pending, _state.fired_at = None, None
    try:
        yield
    finally:
        _state.installed -= 1
        for sig, old in previous.items():
            signal.signal(sig, old if old is not None else signal.SIG_DFL)


def pending_signal() -> int | None:
    """A signal that arrived during a :func:`deferred` block and was not raised yet (or None)."""
    return _state.pending


@contextmanager
def deferred():
    """A block that a signal does not cut in two: a signal arriving inside is raised when the block ends."""
    if not _on_main_thread() or not _state.installed:
        yield
        return
    _state.defer += 1
    try:
        yield
    finally:
        _state.defer -= 1
        if _state.defer == 0 and _state.pending is not None and _state.fired_at is None:
            signum, _state.pending = _state.pending, None
            _state.fired_at = time.monotonic()
            raise Interrupted(signum)


_silenced = set()


def emit(text: str, *, err: bool = False, stream=None) -> bool:
    """Write a line to stdout (``err``: stderr) and flush; never raises.  False if the reader has gone."""
    stream = stream if stream is not None else (sys.stderr if err else sys.stdout)
    if stream is None or id(stream) in _silenced:
        return False
    try:
        stream.write(f"{text}\n")
        stream.flush()
        return True
    except (OSError, ValueError):  # EPIPE (the reader has gone), a closed file, a full disk: output never ends a run
        _silence(stream)
        return False


def _silence(stream) -> None:
    """Point the stream's file descriptor at the null device: later writes (ours, C libraries', the interpreter's
    flush at exit) go nowhere instead of failing."""
    _silenced.add(id(stream))
    try:
        fd = stream.fileno()
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, fd)
        finally:
            os.close(null)
    except (OSError, ValueError, AttributeError):
        pass

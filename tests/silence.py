"""A command's output lines with the time each arrived, from the moment the process is started to its exit
(issue 27: a run is never silent for more than 2 s).

Timestamps are the test's wall clock as each line arrives through the pipe, so a loaded machine is not excused:
the heartbeats' 1 s period leaves 1 s of margin for scheduling delays."""
from __future__ import annotations

import subprocess
import threading
import time

#: Longest silence allowed between two lines (and from start to the first, from the last to the exit), s.
MAX_GAP_S = 2.0


class TimedRun:
    """``lines``: (time, text) from ``<process started>`` to ``<process exited>``; ``stdout`` and ``stderr`` as
    text; ``returncode``."""

    def __init__(self, lines, stderr, returncode):
        self.lines, self.stderr, self.returncode = lines, stderr, returncode
        self.stdout = "\n".join(text for _, text in lines[1:-1])

    def gaps(self) -> list[tuple[float, str]]:
        """(seconds since the line before, the line) for every line after the start."""
        return [(round(b - a, 2), text) for (a, _), (b, text) in zip(self.lines, self.lines[1:])]

    def silences(self, limit: float = MAX_GAP_S) -> list[tuple[float, str]]:
        """The gaps longer than ``limit``, each with the line that ended it."""
        return [(g, text) for g, text in self.gaps() if g > limit]


def timed_run(cmd, *, cwd, env=None, timeout: float = 600.0) -> TimedRun:
    """Run ``cmd`` and time every line of its stdout (stderr is read on a thread: errors only)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1, cwd=cwd,
                            env=env)
    lines = [(t0, "<process started>")]
    err = []
    reader = threading.Thread(target=lambda: err.append(proc.stderr.read()), daemon=True)
    reader.start()
    watchdog = threading.Timer(timeout, proc.kill)
    watchdog.start()
    try:
        for line in proc.stdout:
            lines.append((time.perf_counter(), line.rstrip("\n")))
        code = proc.wait()
        lines.append((time.perf_counter(), "<process exited>"))
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(10)
    return TimedRun(lines, "".join(err), code)

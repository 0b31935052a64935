"""What the add-on's background jobs (a simulation, a sweep) share: their end states, waiting for the end, and
turning the end state into the caller's exception."""
from __future__ import annotations

import time

from ..core.errors import Cancelled

#: The states in which a job has ended.
END_STATES = ("done", "failed", "cancelled")


class BackgroundJob:
    """A job run on a worker thread and stepped from Blender's main thread (``step()`` returns True at the end).
    Subclasses set ``state`` (and ``error`` when failed) and implement ``step``."""

    POLL_S = 0.05
    state: str
    error: BaseException | None

    @property
    def finished(self) -> bool:
        return self.state in END_STATES

    def step(self) -> bool:  # pragma: no cover - every job defines it
        raise NotImplementedError

    def wait(self, timeout_s: float | None = None, poll_s: float | None = None) -> bool:
        """Call :meth:`step` until the job finishes (tests and scripts); returns :attr:`finished`."""
        t_end = None if timeout_s is None else time.perf_counter() + timeout_s
        while not self.step():
            if t_end is not None and time.perf_counter() > t_end:
                break
            time.sleep(self.POLL_S if poll_s is None else poll_s)
        return self.finished

    def raise_outcome(self):
        """The job's error if it failed, Cancelled if it was cancelled; else the job itself."""
        if self.state == "failed":
            raise self.error
        if self.state == "cancelled":
            raise Cancelled()
        return self

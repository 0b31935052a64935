"""What the add-on's background jobs (a simulation, a sweep, the kernel warm-up) share: their end states, waiting
for the end, turning the end state into the caller's exception, and the interface's one running job with the modal
operator's event handling.  Light on purpose (no simulator import beyond its errors): the operators' ``poll`` and
the status bar ask :func:`current_job` from the moment the add-on is enabled, and enabling it must not import the
simulator (numba, SciPy: docs/performance.md, issue 25)."""
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


# The interface's running job (one at a time) and the modal operator's event handling
# ------------------------------------------------------------------------------------------------------------
_current = {"job": None}


def current_job():
    """The job the modal operator is running, or None."""
    job = _current["job"]
    return job if job is not None and not job.finished else None


def set_current_job(job) -> None:
    _current["job"] = job


def handle_modal_event(job: BackgroundJob, event_type: str, event_value: str = "NOTHING") -> str:
    """What the modal operator does with an event: ESC asks the job to cancel (and is consumed), a TIMER event
    advances it; returns the operator status: "RUNNING_MODAL", "PASS_THROUGH" (every other event: the
    interface stays usable), "FINISHED" (results imported) or "CANCELLED" (cancelled or failed: see
    ``job.state``)."""
    if event_type == "ESC" and event_value == "PRESS":
        job.cancel()
        return "RUNNING_MODAL"
    if event_type == "TIMER" and job.step():
        return "FINISHED" if job.state == "done" else "CANCELLED"
    return "PASS_THROUGH"

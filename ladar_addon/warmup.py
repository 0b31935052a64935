"""Compiling the kernels ahead from Blender (``bpy.ops.ladar.warm_up``): core/warmup.py on a worker thread, its
progress in the status bar, ESC or the cancel button stopping it between cases (what it compiled so far stays in
the cache)."""
from __future__ import annotations

import threading

from ..core.errors import Cancelled
from ..core.warmup import cases, warm_up
from .background import BackgroundJob


class WarmUpJob(BackgroundJob):
    """The warm-up as a background job (the interface the simulate operator's modal part and the status bar
    use: ``fraction``, ``status_text``, ``summary``, ``cancel``, ``step``)."""

    def __init__(self):
        self.state = "pending"
        self.error = None
        self.fraction = 0.0
        self.line = "compiling the simulator's kernels (once per install and CPU)"
        self.report = None
        self.total = len(cases())
        self._cancel = threading.Event()
        self._thread = None

    def start(self, threaded: bool = True) -> None:
        self.state = "running"
        if threaded:
            self._thread = threading.Thread(target=self._main, name="ladar-warm-up", daemon=True)
            self._thread.start()
        else:
            self._main()

    def run(self):
        self.start(threaded=False)
        return self.raise_outcome()

    def _main(self):
        try:
            self.report = warm_up(progress=self._progress, cancel=self._cancel.is_set, fraction=self._fraction)
            self.state = "cancelled" if self._cancel.is_set() else "done"
        except Cancelled:
            self.state = "cancelled"
        except BaseException as exc:  # noqa: BLE001 - reported by the operator
            self.error = exc
            self.state = "failed"

    def _progress(self, line: str) -> None:
        self.line = line.removeprefix("warm-up  ")

    def _fraction(self, f: float) -> None:
        self.fraction = f

    def cancel(self) -> None:
        self._cancel.set()

    def step(self) -> bool:
        return self.finished

    def status_text(self) -> str:
        return f"Ladar kernels: {self.line}"

    def summary(self) -> str:
        if self.state == "failed":
            return f"kernel warm-up failed: {self.error}"
        k = self.report or {"compiled": 0, "loaded": 0, "load_and_compile_s": 0.0}
        return (f"kernels ready: {k['compiled']} compiled, {k['loaded']} loaded from the cache "
                f"({k['load_and_compile_s']:.1f} s)")

"""The preview worker's side (core/fileio/preview_worker.py has the command's and the whole story): started as
``python -I -S -c BOOTSTRAP``, it loads the drawing code while the command starts, then draws each order's share of
a run's previews, in ``drawers`` processes at once (itself and forked copies).  Replies, one line each on its
original stdout: ``progress <folder index> <done> <drawer> <pid>`` after each preview, then ``done`` (or
``error …``)."""
from __future__ import annotations

import json
import os
import signal
import sys

from . import preview
from .preview_worker import idle_cores, remove_partial_pngs


def _die_with_parent() -> None:
    """Linux: SIGKILL when the thread that started this process ends (the command killed outright)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - no prctl
        pass


def serve(cfg: dict) -> None:
    """The worker's loop (started by core.fileio.preview_worker.BOOTSTRAP): load the drawing code, then draw each
    order (``{"folders": [...], "share": [k, n]}``, one JSON line on stdin) until stdin ends."""
    for sig in (signal.SIGINT, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)
    _die_with_parent()
    if os.getppid() != cfg.get("parent"):  # the command ended before the line above
        os._exit(0)
    out = os.dup(1)  # the replies' channel; stray prints of libraries go to stderr (the null device)
    os.dup2(2, 1)

    def reply(text: str) -> None:  # (one write of a short line: whole, also from the forked drawers)
        os.write(out, (text + "\n").encode("utf-8"))

    preview.preload()
    # forked drawers only where they die with their worker (PR_SET_PDEATHSIG): else one could still write after
    # the command had taken its worker's share over
    drawers = max(1, int(cfg.get("drawers", 1))) if sys.platform.startswith("linux") else 1
    for line in sys.stdin:
        order = json.loads(line)
        try:
            d = drawers
            if d > 1 and cfg.get("adaptive") and idle_cores() < 1.0:  # (no core to draw on: the fork costs CPU)
                d = 1
            _draw_order(order["folders"], *order["share"], d, reply)
        except Exception as exc:  # reported; the command draws this share itself
            reply("error " + f"{type(exc).__name__}: {exc}".replace("\n", " ")[:500])
            continue
        reply("done")
    os._exit(0)


def _draw_order(folders, k, n, drawers, reply) -> None:
    """Share ``(k, n)`` of the previews of ``folders`` in ``drawers`` processes: this one draws share
    ``(k, n·d)``, forked copies the shares ``(k + n·j, n·d)``; a copy that fails leaves its share to this one."""
    d = drawers if preview.preview_count(folders[0]) > 1 or len(folders) > 1 else 1

    def draw(j):
        for fi, folder in enumerate(folders):
            preview.write_run_previews(folder, share=(k + n * j, n * d), progress=lambda done, total, fi=fi: (
                done and reply(f"progress {fi} {done} {j} {os.getpid()}")))

    children = {}
    for j in range(1, d):
        pid = os.fork()
        if pid == 0:  # a drawer: ends with its share, never returns
            code = 1
            try:
                _die_with_parent()
                draw(j)
                code = 0
            finally:
                os._exit(code)
        children[j] = pid
    draw(0)
    failed = [j for j, pid in children.items() if os.waitpid(pid, 0)[1] != 0]
    if failed:  # (every drawer has ended: nothing is being written)
        for folder in folders:
            remove_partial_pngs(folder)
        for j in failed:
            draw(j)

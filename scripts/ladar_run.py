#!/usr/bin/env python3
"""Run the extension's ``ladar`` command through the ``bpy`` module (no Blender binary needed).

    python scripts/ladar_run.py scene.blend simulate [--out RUN_DIR] [--frame N | --frames 1-100[:STEP]]
                                [--seed N] [--config FILE] [--overwrite | --if-exists {stop,replace,new}]
                                [--sensor NAME] [--clouds {run,frame}] [--no-import] [--no-previews]
    python scripts/ladar_run.py scene.blend sweep sweep.toml --out DIR [--scheduler tcp://HOST:8786]
                                [--workers N] [--restart] [--sensor NAME]
    python scripts/ladar_run.py scene.blend export-config --out settings.toml [--preset NAME]
    python scripts/ladar_run.py scene.blend validate-config settings.toml
    python scripts/ladar_run.py scene.blend simulate --help      (the command's full help)
    python scripts/ladar_run.py warm-up     (compile every system's kernels ahead, with progress; no .blend)

It does what ``blender -b scene.blend -c ladar ...`` does: with ``BLENDER_USER_RESOURCES`` pointing at a fresh
temporary folder (set before ``import bpy``), it installs this repository as an extension in a local extension
repository, enables it as ``bl_ext.ladar_dev.ladar_simulator``, opens the .blend file and calls the command
handler the extension registers (a usage error or ``--help`` is answered before Blender starts, with the same
parser).  A ``simulate`` that draws PNG previews starts their worker process before Blender, where a core is idle
(core.fileio.preview_worker: it loads matplotlib meanwhile; the command ends it).  Exit codes: 0 success, 1 user error (one line on stderr), 2 usage error,
130 interrupted (Ctrl-C), 143 terminated (SIGTERM: batch schedulers, ``timeout``), 129 hung up (SIGHUP).  An
interrupted run leaves nothing behind: its staging folder and the temporary Blender user folder are removed
(after a SIGKILL, which cannot be caught, the next run removes them).
"""
from __future__ import annotations

import signal as _signal
import sys

#: Ctrl-C before the command's own handlers are in place is recorded here and acted on at the next step: a
#: KeyboardInterrupt raised by Python's default handler inside a weakref callback of the import machinery is only
#: printed ("Exception ignored in ...") and lost, and the run would go on.
_EARLY_SIGINT = []
if _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler:  # (not where SIGINT is ignored)
    _signal.signal(_signal.SIGINT, lambda signum, frame: _EARLY_SIGINT.append(signum))

try:  # every import inside: Ctrl-C within the first milliseconds exits 130 without a traceback
    import os
    import tempfile
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import blender_env  # noqa: E402  (puts the repository on sys.path: core.process is standard library only)
    import core.process as process  # noqa: E402
except KeyboardInterrupt:  # Ctrl-C within the first milliseconds: nothing started yet
    sys.exit(130)
if _EARLY_SIGINT:  # (the same, recorded by the handler above)
    sys.exit(130)

USAGE = ("usage: ladar_run.py SCENE.blend {simulate,sweep,export-config,validate-config} [options]\n"
         "       ladar_run.py warm-up\n"
         "       (ladar_run.py -h: this script; ladar_run.py SCENE.blend simulate -h: the command's options)")


class step:
    """``with step("loading Blender (bpy)"):`` prints ``ladar: loading Blender (bpy) …`` before a slow start-up step
    and, while it lasts, ``ladar: loading Blender (bpy) … 1 s``, ``… 2 s`` from a daemon thread every
    ``heartbeat_s`` (issue 27: start-up is never silent for more than 2 s).  The thread needs the GIL to print;
    ``import bpy`` and the extension's registration release it often enough for a line a second (measured: the
    largest gap in a flash-demo run is the heartbeat period plus a few tens of milliseconds)."""

    def __init__(self, what: str, heartbeat_s: float = 1.0):
        self.what, self.heartbeat_s = what, heartbeat_s
        import threading

        self._done = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="ladar-startup-heartbeat", daemon=True)

    def _beat(self) -> None:
        import time

        t0 = time.monotonic()
        while not self._done.wait(self.heartbeat_s):
            process.emit(f"ladar: {self.what} \u2026 {time.monotonic() - t0:.0f} s")

    def __enter__(self):
        process.emit(f"ladar: {self.what} \u2026")
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._done.set()
        self._thread.join()


class BlendFileError(Exception):
    """The .blend file cannot be opened (truncated, corrupt, not a .blend file)."""


def open_blend(bpy, path: Path) -> None:
    """Open ``path`` in Blender.  Raises BlendFileError with Blender's reason on one line; Blender's own report of
    the failure (printed on stdout) is dropped, and its output of a file that opens is passed through."""
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as log:
        os.dup2(log.fileno(), 1)
        try:
            bpy.ops.wm.open_mainfile(filepath=str(path.resolve()), load_ui=False)
        except RuntimeError as exc:
            reason = str(exc).splitlines()[-1] if str(exc).strip() else type(exc).__name__
            for noise in (f" '{path.resolve()}'", f' in file "{path.resolve()}"', "Error: "):
                reason = reason.split("failed: ")[-1].replace(noise, "")
            raise BlendFileError(f"{path} is not a readable .blend file ({reason[:200].strip(' :.')})") from None
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
        log.seek(0)
        try:
            sys.stdout.buffer.write(log.read())
            sys.stdout.flush()
        except (OSError, ValueError):  # the reader has gone: output never ends a run
            pass


def check_command_line(command) -> int | None:
    """Parse the command line with the command's own parser (ladar_addon/cli_args.py: the standard library only)
    before Blender starts: a usage error (argparse's message, exit 2) or ``--help`` (exit 0) is answered here, in
    0.1 s instead of the 1.5 s of CPU of starting Blender and enabling the extension first; None when the command
    line parses (the command handler parses it again: the settings, files and scene are checked there)."""
    from ladar_addon.cli_args import build_parser  # (REPO_ROOT is on sys.path: blender_env)

    try:
        build_parser().parse_args(list(command))
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    return None


def starts_previews(command) -> bool:
    """The command will draw PNG previews (``simulate`` without ``--no-previews``): its preview workers start
    before Blender does (core.fileio.preview_worker)."""
    from ladar_addon.cli_args import build_parser

    try:
        args = build_parser().parse_args(list(command))
    except SystemExit:  # pragma: no cover - checked by check_command_line first
        return False
    return args.command == "simulate" and not args.no_previews


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        process.emit(__doc__ if argv else USAGE, err=not argv)
        return 0 if argv else 2
    blend, command = Path(argv[0]), argv[1:]
    if argv[0] == "warm-up":  # needs no scene
        blend, command = None, argv
    elif blend.suffix.lower() != ".blend" or not blend.is_file():
        process.emit(f"ladar: error: {blend} is not an existing .blend file", err=True)
        return 1
    usage = check_command_line(command)
    if usage is not None:  # a usage error (2) or --help (0): answered without starting Blender
        return usage

    pool = None
    with process.interrupts_as_exceptions():
        try:
            if _EARLY_SIGINT:  # Ctrl-C before the handlers above were in place
                raise process.Interrupted(_EARLY_SIGINT[0])
            with process.deferred():  # starting Blender is not cut in two: a signal meanwhile ends it right after
                if starts_previews(command):  # they load matplotlib on the other core while Blender starts
                    from core.fileio.preview_worker import PreviewPool

                    pool = PreviewPool.start()
                blender_env.isolate_user_resources()  # a temporary folder, removed at exit
                with step("loading Blender (bpy)"):
                    import bpy
                with step("installing the extension into a temporary user folder"):
                    addon = blender_env.install_extension()
                if blend is not None:
                    process.emit(f"ladar: opening {blend.name} \u2026")  # (fast: its output is held until it ends)
                    open_blend(bpy, blend)
            return addon.ladar_addon.cli.cli_handler(command, preview_pool=pool)
        except BlendFileError as exc:
            process.emit(f"ladar: error: {exc}", err=True)
            return 1
        except KeyboardInterrupt as exc:  # while Blender was starting (the command reports its own)
            how = getattr(exc, "signal_name", "SIGINT")
            process.emit("ladar: interrupted" + (f" ({how})" if how != "SIGINT" else "") + ": nothing was written",
                         err=True)
            return process.exit_code(exc)
        finally:
            if pool is not None:  # (the command ended them; not when it failed before it ran)
                pool.kill()


def exit_now(code: int) -> None:
    """Exit with ``code`` once the exit handlers have run (bpy's, which ends Blender; then the removal of the
    temporary Blender user folder), without the interpreter's finalization: freeing every module and object one
    by one (numba, llvmlite, SciPy, matplotlib, Blender's data) took 0.8-2 s after the summary's last line, in
    silence (issue 27: from process start to exit, never more than 2 s without a line), and every output is
    closed by then.  After an interruption (exit 129/130/143) it also does not wait for the worker threads
    (core/threads.py), which may be in the middle of a kernel's compile for seconds."""
    import atexit

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):  # (what the exit handlers printed)
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


if __name__ == "__main__":
    exit_now(main())

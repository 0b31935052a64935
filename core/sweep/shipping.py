"""Getting the core onto Dask workers, with no manual copying and no Blender.

The core imports itself only relatively, so a copy of its ``.py`` files works under any package name.
:func:`stage_core` copies them to ``<tmp>/ladar-sweep-core-<uid>/<name>-pkg/<name>/`` with the versioned name
``ladar_core_<hash of the files>`` (so a long-lived cluster never runs stale code: new code, new name) and puts
the outer folder on this process's ``sys.path``.

A separately started ``dask scheduler`` unpickles every task graph it receives (``Scheduler.update_graph``), so a
task must never name a function of the shipped core to it: the scheduler has neither the core nor this project.
:func:`shipped_call` wraps ``<name>.sweep.task.run_task`` and its arguments in bytes, and the task the client
submits is ``pickle.loads(those bytes)``: the scheduler sees a standard-library function and a bytes argument; a
worker, loading the bytes, imports the shipped core and makes the call (pickle's ``REDUCE``: the loaded object is
the call's result).

:func:`ship_core` makes that package importable on every worker: the workers of a LocalCluster started by this
process inherit ``sys.path``; any other worker gets the package's files, zipped, through a ``distributed`` worker
plugin (:func:`core_plugin`: held by the scheduler as bytes it never unpickles, set up in every worker process that
runs or joins later, a restarted one included), which unpacks them into the same per-user folder
``<tmp>/ladar-sweep-core-<uid>/<name>-pkg/`` (once per version and machine: a worker on the client's machine finds
the client's copy) and puts it on the worker's path.  No worker restarts.  The folder's path does not change from
one worker process or cluster to the next, so numba's cache of compiled kernels (keyed by the source's path) serves
every later worker of the same version: only the first worker process of a machine compiles them.

This module uses only the standard library (and ``distributed`` inside :func:`core_plugin`): it is sent to the
workers by value (the workers do not have the core yet when :func:`can_import` and the plugin run there).
"""
from __future__ import annotations

import hashlib
import io
import os
import pickle
import shutil
import sys
import tempfile
import zipfile
from pathlib import Path


def core_source_dir() -> Path:
    return Path(__file__).resolve().parents[1]


def core_digest(src: Path | None = None) -> str:
    """A short hash of the core's ``.py`` files (paths and contents)."""
    src = src or core_source_dir()
    h = hashlib.blake2b(digest_size=6)
    for f in sorted(src.rglob("*.py")):
        if "__pycache__" in f.parts:
            continue
        h.update(str(f.relative_to(src).as_posix()).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def staging_folder(name: str) -> Path:
    """The per-user folder that holds the core version ``name`` (``<name>/`` inside; the folder is put on the path)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return Path(tempfile.gettempdir()) / f"ladar-sweep-core-{uid}" / f"{name}-pkg"  # not importable itself


def _install(outer: Path, name: str, fill) -> None:
    """Create ``outer/name`` once: ``fill(folder)`` writes the files into a hidden folder, renamed into place (a
    process that finds ``outer/name/__init__.py`` finds a complete package)."""
    if not (outer / name / "__init__.py").is_file():
        outer.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".stage-", dir=outer))
        try:
            fill(tmp)
            os.rename(tmp, outer / name)
        except OSError:  # another process installed the same version meanwhile
            if not (outer / name / "__init__.py").is_file():
                raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    _write_bytecode(outer / name)
    if str(outer) not in sys.path:
        sys.path.insert(0, str(outer))
    import importlib

    importlib.invalidate_caches()


def _write_bytecode(package: Path) -> None:
    """Compile the installed package's modules whose bytecode is missing or out of date (``__pycache__`` beside
    them; each file written to a temporary file and renamed, so processes doing it at once are safe).  Every worker
    process imports the package from this folder: where Python does not write bytecode itself
    (``PYTHONDONTWRITEBYTECODE``, a read-only temporary folder for the first one) each of them compiled every
    source of the core again, 0.3-0.5 s of CPU per worker process.  A file that cannot be written costs only that."""
    import compileall

    try:
        compileall.compile_dir(package, quiet=2, workers=1)
    except OSError:
        pass


def _core_files(src: Path):
    for f in sorted(src.rglob("*.py")):
        if "__pycache__" not in f.parts:
            yield f, f.relative_to(src)


def stage_core() -> tuple:
    """Stage the core under its versioned name (once per version); returns (package name, the outer folder)."""
    name = f"ladar_core_{core_digest()}"
    outer = staging_folder(name)
    src = core_source_dir()

    def fill(folder: Path) -> None:
        for f, rel in _core_files(src):
            dst = folder / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(f, dst)

    _install(outer, name, fill)
    return name, outer


def core_zip(folder: Path) -> bytes:
    """The ``.py`` files of the staged package ``folder``, zipped (paths relative to it)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for f, rel in _core_files(folder):
            z.write(f, rel.as_posix())
    return buf.getvalue()


def install_core(name: str, data: bytes) -> Path:
    """Runs on a worker: unpack the zipped core ``name`` into :func:`staging_folder` (unless there) and put it on
    ``sys.path``; returns the folder."""
    outer = staging_folder(name)

    def fill(folder: Path) -> None:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            for member in z.namelist():  # our own archive; still, nothing outside the folder
                if member.startswith("/") or ".." in Path(member).parts:
                    raise ValueError(f"unexpected path in the shipped core: {member!r}")
            z.extractall(folder)

    _install(outer, name, fill)
    return outer


def core_plugin(name: str, data: bytes):
    """A ``distributed`` worker plugin that installs the zipped core ``name`` in every worker process (running now
    or started later) with :func:`install_core`.  Its class is made here so that it travels by value."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class ShipLadarCore(WorkerPlugin):
        idempotent = True  # registered again by a later sweep of the same version: nothing to do

        def __init__(self):
            self.package, self.data = name, data

        def setup(self, worker):
            install_core(self.package, self.data)

    return ShipLadarCore()


class _Call:
    """``pickle.loads(pickle.dumps(_Call(func, args)))`` is ``func(*args)``: pickled as the call itself
    (``__reduce__``), not as an instance of this class (loading never needs this module)."""

    def __init__(self, func, args):
        self.func, self.args = func, tuple(args)

    def __reduce__(self):
        return self.func, self.args


def shipped_call(func, *args) -> bytes:
    """Bytes whose ``pickle.loads`` calls ``func(*args)`` and returns its result.  ``func`` is pickled by reference
    (module and name: the shipped core's, imported by the worker that loads the bytes), the arguments by value;
    submit ``(pickle.loads, shipped_call(...))``: a task the scheduler can unpickle without the core."""
    return pickle.dumps(_Call(func, args), protocol=pickle.HIGHEST_PROTOCOL)


def can_import(name: str) -> bool:
    """Runs on a worker: can it import the shipped core ``name`` (its sweep task module)?"""
    import importlib.util

    try:
        return importlib.util.find_spec(f"{name}.sweep.task") is not None
    except ImportError:
        return False


def ship_core(client) -> str:
    """Make the staged core importable on every worker of ``client`` (:func:`core_plugin` where a worker cannot
    import it yet); returns its package name.  Raises RuntimeError if a worker still cannot import it."""
    import cloudpickle

    name, outer = stage_core()
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # can_import and the plugin travel by value
    try:
        have = client.run(can_import, name)
        if not have or not all(have.values()):
            client.register_plugin(core_plugin(name, core_zip(outer / name)), name=f"ladar-ship-{name}")
            have = client.run(can_import, name)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    missing = sorted(k for k, v in have.items() if not v)
    if missing:
        raise RuntimeError(f"the workers {', '.join(missing)} cannot import the shipped core {name}")
    return name

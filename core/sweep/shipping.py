"""Getting the core onto Dask workers, with no manual copying and no Blender.

The core imports itself only relatively, so a copy of its ``.py`` files works under any package name.
:func:`stage_core` copies them to ``<tmp>/ladar-sweep-core-<uid>/<name>-pkg/<name>/`` with the versioned name
``ladar_core_<hash of the files>`` (so a long-lived cluster never runs stale code: new code, new name) and puts
the outer folder on this process's ``sys.path``; the client then submits ``<name>.sweep.task.run_task``.

:func:`ship_core` makes that package importable on every worker: the workers of a LocalCluster started by this
process inherit ``sys.path``; any other worker gets the folder through ``distributed``'s ``UploadDirectory``
plugin (zipped, sent through the scheduler, unpacked into each worker's local directory and put on its path; the
workers restart once to pick it up, and a worker that joins or restarts later gets it too).

This module uses only the standard library: it is sent to the workers by value (the workers do not have the
core yet when :func:`can_import` runs there).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
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


def stage_core() -> tuple:
    """Stage the core under its versioned name (once per version); returns (package name, the outer folder)."""
    name = f"ladar_core_{core_digest()}"
    uid = os.getuid() if hasattr(os, "getuid") else 0
    outer = Path(tempfile.gettempdir()) / f"ladar-sweep-core-{uid}" / f"{name}-pkg"  # not importable itself
    if not (outer / name / "__init__.py").is_file():
        outer.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".stage-", dir=outer))
        src = core_source_dir()
        for f in src.rglob("*.py"):
            if "__pycache__" in f.parts:
                continue
            dst = tmp / f.relative_to(src)
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(f, dst)
        try:
            os.rename(tmp, outer / name)
        except OSError:  # another process staged the same version meanwhile
            shutil.rmtree(tmp, ignore_errors=True)
    if str(outer) not in sys.path:
        sys.path.insert(0, str(outer))
    return name, outer


def can_import(name: str) -> bool:
    """Runs on a worker: can it import the shipped core ``name`` (its sweep task module)?"""
    import importlib.util

    try:
        return importlib.util.find_spec(f"{name}.sweep.task") is not None
    except ImportError:
        return False


def ship_core(client) -> str:
    """Make the staged core importable on every worker of ``client``; returns its package name.  Raises
    RuntimeError if a worker still cannot import it."""
    import cloudpickle

    name, outer = stage_core()
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # can_import travels by value
    try:
        have = client.run(can_import, name)
        if not have or not all(have.values()):
            from distributed.diagnostics.plugin import UploadDirectory

            client.register_plugin(UploadDirectory(str(outer), update_path=True, restart_workers=True))
            have = client.run(can_import, name)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    missing = sorted(k for k, v in have.items() if not v)
    if missing:
        raise RuntimeError(f"the workers {', '.join(missing)} cannot import the shipped core {name}")
    return name

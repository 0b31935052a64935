"""Run this extension inside the ``bpy`` module the way Blender itself installs extensions.

Used by the add-on tests and by ``scripts/ladar_run.py``.  Order matters:

1. :func:`isolate_user_resources` — point ``BLENDER_USER_RESOURCES`` at a fresh temporary folder *before*
   ``import bpy`` (preferences, extension repositories and caches then never touch the user's own Blender);
2. :func:`install_extension` — create a local extension repository whose folder contains ``ladar_simulator``
   (a directory of symlinks to this repository's package files, without ``.venv``/``.git``/tests), register
   the repository in the preferences and enable ``bl_ext.<repo>.ladar_simulator`` with ``addon_utils``.

The add-on is then imported as ``bl_ext.ladar_dev.ladar_simulator`` (its core as
``bl_ext.ladar_dev.ladar_simulator.core``), exactly as an installed extension.
"""
from __future__ import annotations

import atexit
import fnmatch
import os
import shutil
import sys
import tempfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.append(str(REPO_ROOT))
import core.fileio.locks as locks  # noqa: E402  (standard library only: safe before `import bpy`)

TEMP_PREFIX = "ladar_blender_"
EXTENSION_ID = "ladar_simulator"
REPO_MODULE = "ladar_dev"
ADDON_MODULE = f"bl_ext.{REPO_MODULE}.{EXTENSION_ID}"

#: What the installed extension is made of: these entries of the repository (paths or glob patterns relative to
#: its root), nothing else.  Whatever else a checkout holds — tests, scripts, docs, benchmarks, run folders, a
#: developer's own folders — stays out of the development install and of the extension zips.
PACKAGE_PATHS = ("__init__.py", "blender_manifest.toml", "README.md", "core", "ladar_addon", "operators", "panels",
                 "presets", "sample_blends/*.blend")
#: Never packaged, at any depth of those folders.
PACKAGE_IGNORE = ("__pycache__", "*.pyc", ".*", "*.blend1", "*.zip")
#: Tracked top-level entries that are deliberately not packaged (tests/test_packaging.py checks that every tracked
#: entry is in PACKAGE_PATHS or here, so a new one is a decision).
DEVELOPMENT_ONLY = (".ci", ".gitignore", "bench", "docs", "pyproject.toml", "requirements.txt",
                    "requirements-worker.txt", "requirements-clients.txt", "requirements-validation.txt", "scripts",
                    "tests",
                    "sample_blends/build_samples.py")


def _ignored(name: str) -> bool:
    return any(fnmatch.fnmatch(name, pattern) for pattern in PACKAGE_IGNORE)


def package_entries(source: Path = REPO_ROOT) -> list[Path]:
    """The files and folders :data:`PACKAGE_PATHS` names in ``source`` (patterns expanded), in order.

    Raises FileNotFoundError if one is missing (a broken checkout must not give a broken package)."""
    source = Path(source)
    entries = []
    for pattern in PACKAGE_PATHS:
        hits = sorted(p for p in source.glob(pattern) if not _ignored(p.name))
        if not hits:
            raise FileNotFoundError(f"the extension needs {pattern}, missing from {source}")
        entries += hits
    return entries


def package_files(source: Path = REPO_ROOT) -> list[Path]:
    """Every file of the package, relative to ``source`` (folders walked, :data:`PACKAGE_IGNORE` skipped)."""
    source = Path(source)
    files = []
    for entry in package_entries(source):
        if entry.is_dir():
            for root, dirs, names in os.walk(entry):
                dirs[:] = sorted(d for d in dirs if not _ignored(d))
                files += [Path(root, n).relative_to(source) for n in sorted(names) if not _ignored(n)]
        else:
            files.append(entry.relative_to(source))
    return files


def isolate_user_resources(path: str | os.PathLike | None = None) -> Path:
    """Set ``BLENDER_USER_RESOURCES`` to ``path`` (default: a new temporary folder, removed when the process
    exits — after bpy's own exit handlers, which are registered later and so run first).  Call before
    ``import bpy``.

    The temporary folder also holds Blender's session temporary folder (``TMPDIR`` points inside it), and it is
    held by this process (core.fileio.locks): if the process is killed (SIGKILL), the next call removes it."""
    if "bpy" in sys.modules:
        current = os.environ.get("BLENDER_USER_RESOURCES")
        if current and Path(current).name.startswith(TEMP_PREFIX):
            return Path(current)
        raise RuntimeError("bpy is already imported: BLENDER_USER_RESOURCES must be set before `import bpy`")
    if path is None:
        root = Path(tempfile.mkdtemp(prefix=TEMP_PREFIX))
        atexit.register(shutil.rmtree, root, ignore_errors=True)
        lock = locks.lock_new_folder(root, purpose="temporary Blender user folder")
        atexit.register(lock.release)  # runs before the removal (atexit: last registered, first run)
        remove_abandoned_user_resources(root.parent)
        session_tmp = root / "tmp"  # Blender's session temporary folder goes inside (removed with it)
        session_tmp.mkdir()
        for var in ("TMPDIR", "TEMP", "TMP") if os.name == "nt" else ("TMPDIR",):
            os.environ[var] = str(session_tmp)
    else:
        root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    os.environ["BLENDER_USER_RESOURCES"] = str(root)
    return root


def remove_abandoned_user_resources(folder) -> list[Path]:
    """Remove the temporary Blender user folders in ``folder`` whose process is gone (killed before it could
    remove its own); folders of running processes, and folders without an owner file, are left alone."""
    removed = []
    for entry in Path(folder).glob(TEMP_PREFIX + "*"):
        if entry.is_dir() and (entry / locks.OWNER_FILE).is_file() and locks.remove_if_abandoned(entry):
            removed.append(entry)
    return removed


def link_package(repo_dir: Path, source: Path = REPO_ROOT) -> Path:
    """Create ``repo_dir/ladar_simulator`` holding symlinks to the package's entries (:data:`PACKAGE_PATHS`).

    Falls back to copying where symlinks are not available.  Returns the package folder.
    """
    pkg = Path(repo_dir) / EXTENSION_ID
    if pkg.exists():
        shutil.rmtree(pkg)
    pkg.mkdir(parents=True)
    for entry in package_entries(source):
        target = pkg / entry.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            target.symlink_to(entry, target_is_directory=entry.is_dir())
        except OSError:
            if entry.is_dir():
                shutil.copytree(entry, target, ignore=shutil.ignore_patterns(*PACKAGE_IGNORE))
            else:
                shutil.copy2(entry, target)
    return pkg


def install_extension(source: Path = REPO_ROOT):
    """Register a local extension repository containing this package and enable the add-on.

    Returns the enabled add-on module (``bl_ext.ladar_dev.ladar_simulator``).
    """
    if "BLENDER_USER_RESOURCES" not in os.environ:
        raise RuntimeError("call isolate_user_resources() before importing bpy")
    import addon_utils
    import bpy

    repo_dir = Path(os.environ["BLENDER_USER_RESOURCES"]) / "ladar_extension_repo"
    link_package(repo_dir, source)
    repos = bpy.context.preferences.extensions.repos
    if repos.get(REPO_MODULE) is None and not any(r.module == REPO_MODULE for r in repos):
        repo = repos.new(name="Ladar (development)", module=REPO_MODULE, custom_directory=str(repo_dir),
                         source='USER')
        repo.use_custom_directory = True
    enable_addon()
    return sys.modules[ADDON_MODULE]


def enable_addon():
    import addon_utils

    def fail(ex):
        raise ex

    mod = addon_utils.enable(ADDON_MODULE, default_set=True, handle_error=fail)
    if mod is None:
        raise RuntimeError(f"could not enable {ADDON_MODULE}")
    return mod


def disable_addon():
    import addon_utils

    def fail(ex):
        raise ex

    addon_utils.disable(ADDON_MODULE, default_set=True, handle_error=fail)


def addon_module():
    """The enabled add-on package module."""
    return sys.modules[ADDON_MODULE]

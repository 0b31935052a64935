"""Run folders: claimed before the run, built hidden, renamed into place; never anything else replaced.  Single
files (previews, LAS, exported configs): :func:`write_file_atomically`.

The one implementation of the staged run folder (used by ``fileio.run_folder.write_run``,
``core.run.run_simulation``, ``sequence.run_sequence``, the add-on's job and the command line).  Rules:

* **Claim first.**  A run claims its folder's name when it starts, by creating the hidden staging folder
  ``.<name>.<hash>.ladar-staging`` beside it (``mkdir`` is atomic).  Inside is an owner file, locked by the
  running process for as long as the claim lives (``flock``; released by the kernel when the process ends,
  even by SIGKILL) and recording pid, host and start time.  A second run for the same name finds the claim held
  and refuses (``if_exists="stop"``/``"replace"``) or takes the next free name (``"new"``: ``<name>_2`` …).
* **Replace only a run.**  With ``replace`` an existing folder is replaced only when it is recognisably a run of
  this tool (its ``metadata.json`` has a ``format`` starting with ``ladar-``), not a mount point, and neither
  the current folder nor one containing it.  Anything else is refused, naming it, before any work.
* **Build hidden, rename into place.**  The products go into ``<staging>/run``; :meth:`RunClaim.commit` moves
  the previous run (if any) into the staging folder, renames the new one into place and removes the old one.
  A failed, cancelled or interrupted run removes its staging folder and leaves nothing.
* **Clean what dead runs left.**  Every claim first removes the staging folders beside it whose owner is gone
  (lock free; without a lock, same host and that pid no longer running) — and only those.  If a run died
  between its two renames, the previous run it was replacing is put back.
* **Names fit.**  The staging name is short whatever the run name (a prefix and a hash), so a run name up to
  the file system's limit (255 bytes) works.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import secrets
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

from ..errors import ConfigError
from ..process import deferred
from .locks import OWNER_FILE, FolderLock, lock_new_folder, remove_if_abandoned, removal_path

STAGING_SUFFIX = ".ladar-staging"
#: Longest file name (bytes) where the file system does not say.
DEFAULT_NAME_MAX = 255

# ------------------------------------------------------------------------------------------------------------
# Temporary files and folders (made with the user's umask, renamed into place when complete)
# ------------------------------------------------------------------------------------------------------------
def new_temp_dir(parent, prefix: str) -> Path:
    """A new empty folder ``parent/<prefix><random>``, made by ``mkdir`` and so with the user's umask (0755 under
    umask 022).  ``tempfile.mkdtemp`` makes 0700: a run folder renamed from it stays private to its owner."""
    parent = Path(parent)
    for _ in range(100):
        path = parent / f"{prefix}{secrets.token_hex(6)}"
        try:
            os.mkdir(path)  # mode 0o777 & ~umask
        except FileExistsError:
            continue
        return path
    raise FileExistsError(f"no free temporary folder name {prefix}… in {parent}")


def new_temp_file(parent, prefix: str, suffix: str = "") -> tuple[int, Path]:
    """(open write-only descriptor, path) of a new empty file ``parent/<prefix><random><suffix>`` created with the
    user's umask (0644 under umask 022; ``tempfile.mkstemp`` makes 0600, which a file renamed into place keeps)."""
    parent = Path(parent)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        path = parent / f"{prefix}{secrets.token_hex(6)}{suffix}"
        try:
            return os.open(path, flags, 0o666), path  # mode 0o666 & ~umask
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary file name {prefix}…{suffix} in {parent}")


@contextmanager
def naming(path):
    """An OSError raised in the block names ``path`` (``np.save``, ``np.savez`` and ``json.dump`` raise a full disk
    as ``[Errno 28] No space left on device`` without the file): every writer's failure reads the same."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None:
            raise
        if exc.errno is not None:
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        if "requested and" in str(exc):  # NumPy's short write ("65536 requested and 8160 written"): a full disk
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({exc})", str(path)) from None
        raise OSError(errno.EIO, str(exc), str(path)) from None


def write_file_atomically(path, write, *, overwrite: bool = True, suffix: str = ".tmp") -> Path:
    """Write the single file ``path`` complete or not at all: ``write(f)`` fills a hidden temporary file
    ``.<name>.<random><suffix>`` in the same folder (binary, the user's umask), which then takes the name.

    ``overwrite``: replace an existing file (``os.replace``); otherwise the file is linked into place, which fails
    with FileExistsError if the name exists, even when it appears while writing (on a file system without hard
    links: replaced after a check).  A failure leaves neither a temporary file nor half a file."""
    path = Path(path)
    if not overwrite and (path.exists() or path.is_symlink()):
        raise FileExistsError(f"{path} exists")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = new_temp_file(path.parent, f".{path.name[:100]}.", suffix)
    try:
        with naming(path), os.fdopen(fd, "wb") as f:
            write(f)
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # atomic, and fails if the name exists
            except FileExistsError:
                raise FileExistsError(f"{path} exists (it was created meanwhile)") from None
            except OSError:  # no hard links on this file system
                os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path


# ------------------------------------------------------------------------------------------------------------
# Run folders
# ------------------------------------------------------------------------------------------------------------
def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return DEFAULT_NAME_MAX


def staging_path(out: Path) -> Path:
    """The hidden staging folder of run folder ``out``: ``.<prefix>.<hash>.ladar-staging`` (≤ 140 bytes)."""
    name = out.name
    prefix = os.fsencode(name)[:100].decode("utf-8", "ignore") if os.name != "nt" else name[:100]
    digest = hashlib.sha256(os.fsencode(name)).hexdigest()[:16]
    return out.with_name(f".{prefix}.{digest}{STAGING_SUFFIX}")


def is_run_folder(path) -> bool:
    """A folder this tool wrote: a ``metadata.json`` whose ``format`` starts with ``ladar-``."""
    path = Path(path)
    meta = path / "metadata.json"
    try:
        if not path.is_dir() or not meta.is_file() or meta.stat().st_size > 64 * 2**20:
            return False
        data = json.loads(meta.read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError, RecursionError):
        return False
    return isinstance(data, dict) and isinstance(data.get("format"), str) and data["format"].startswith("ladar-")


def _refuse(out: Path, allowed: str):
    raise ConfigError("out", str(out), allowed)


def refuse_symlink(out: Path) -> None:
    """A run folder given as a symbolic link is refused (ConfigError naming where it points), dangling or not:
    the run would be written wherever the link points (a dangling link's target created without a word).  Links
    among the folders above it are followed as usual."""
    if out.is_symlink():
        try:
            target = os.readlink(out)
        except OSError:
            target = "?"
        _refuse(out, f"a folder path that is not a symbolic link (this one points to {target}"
                     f"{'' if out.exists() else ', which does not exist'}): give the real folder's path")


def _checked_name(out_dir) -> Path:
    """The absolute path, if its name fits the file system (else ConfigError)."""
    out = Path(os.path.abspath(Path(out_dir).expanduser()))
    if not out.name:
        _refuse(out, "a run folder path with a name (not a file system root)")
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    limit = _name_max(parent)
    if len(os.fsencode(out.name)) > limit:
        _refuse(out, f"a folder name of at most {limit} bytes (this one has {len(os.fsencode(out.name))})")
    return out


def _numbered(base: Path):
    """``base``, ``<base>_2``, ``<base>_3`` … (each checked to fit the file system)."""
    for k in range(1, 10_000):
        yield _checked_name(base if k == 1 else base.with_name(f"{base.name}_{k}"))
    _refuse(base, "a folder name with a free numbered variant (<name>_2 … <name>_9999 are all taken)")


def free_run_path(out_dir, taken=None) -> Path:
    """The first of ``out_dir``, ``<out_dir>_2`` … that does not exist (and that ``taken(path)`` does not
    declare taken).  Only a claim (:func:`claim_run_dir` with ``if_exists="new"``) makes it this run's."""
    for cand in _numbered(_checked_name(out_dir)):
        if not (cand.exists() or cand.is_symlink() or (taken is not None and taken(cand))):
            return cand


def check_run_dir(out_dir, overwrite: bool) -> Path:
    """Refuse (ConfigError, nothing written) a run folder that may not be written: its name is too long, it
    exists and ``overwrite`` is off, or it exists and is not a run of this tool that may be replaced (see
    :func:`check_replaceable`).  Returns the absolute path."""
    out = _checked_name(out_dir)
    refuse_symlink(out)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            _refuse(out, "a folder path (a file of that name exists)")
        if not overwrite:
            _refuse(out, "a run folder that does not exist yet (or overwrite it: --overwrite, "
                         "Scene > Ladar > If Exists: Replace or New Name)")
        check_replaceable(out)
    return out


def check_replaceable(out: Path) -> None:
    """Refuse replacing ``out`` unless it is a previous run of this tool that can be swapped out."""
    out = Path(out)
    real = Path(os.path.realpath(out))
    try:
        cwd = Path(os.path.realpath(os.getcwd()))
    except OSError:  # pragma: no cover - the current folder was removed
        cwd = None
    if cwd is not None and (real == cwd or real in cwd.parents):
        _refuse(out, "a run folder to replace, not the current folder or one containing it (choose a new "
                     "folder name)")
    if os.path.ismount(real):
        _refuse(out, "a run folder to replace, not a mount point (write the run into a folder inside it)")
    if not is_run_folder(out):
        _refuse(out, "an existing folder is replaced only if it is a previous run of this simulator (its "
                     "metadata.json); this one is not: choose another folder or remove it yourself")


def _restore_previous(staging: Path, record: dict) -> None:
    """A run died between its two renames: put the run it was replacing back in place."""
    old, name = staging / "old", record.get("run")
    if not name or not old.is_dir():
        return
    out = staging.with_name(name)
    if not out.exists():
        os.rename(old, out)


def remove_abandoned_staging(parent) -> list[Path]:
    """Remove the staging folders in ``parent`` left by runs whose process is gone (see module doc)."""
    removed = []
    try:
        entries = [e for e in os.scandir(parent) if e.name.endswith(STAGING_SUFFIX) and e.is_dir()]
    except OSError:
        return removed
    for entry in entries:
        if remove_if_abandoned(entry.path, restore=_restore_previous):
            removed.append(Path(entry.path))
    return removed


class RunClaim:
    """This process's right to write run folder :attr:`path`: build the run in :attr:`work` (it does not exist
    yet: create it, or let ``write_run`` create it), then :meth:`commit`; :meth:`release` always (or use
    ``with``)."""

    def __init__(self, path: Path, staging: Path, lock: FolderLock, replace: bool, created: list[Path]):
        self.path, self.staging, self.replace = path, staging, replace
        self.work = staging / "run"
        self._lock, self._created, self.committed = lock, created, False
        _live_claims.add(self)

    def commit(self) -> Path:
        """Rename :attr:`work` into place.  An existing folder is replaced only if this claim may replace it and
        it (still) is a run of this tool; otherwise ConfigError and the work stays in staging."""
        out, old = self.path, self.staging / "old"
        if not self.work.is_dir():
            raise FileNotFoundError(errno.ENOENT, "the run was not built", str(self.work))
        with deferred():
            if out.exists() or out.is_symlink():
                if not self.replace:
                    _refuse(out, "a run folder that does not exist yet (it was created by someone else during "
                                 "the run)")
                check_replaceable(out)
                os.rename(out, old)
                try:
                    os.rename(self.work, out)
                except BaseException:
                    os.rename(old, out)
                    raise
            else:
                try:
                    os.rename(self.work, out)
                except OSError as exc:
                    if exc.errno in (errno.ENOTEMPTY, errno.EEXIST):
                        _refuse(out, "a run folder that does not exist yet (it was created by someone else "
                                     "during the run)")
                    raise
            self.committed = True
        shutil.rmtree(old, ignore_errors=True)
        return out

    def release(self) -> None:
        """Remove the staging folder (and, if nothing was committed, the empty folders the claim created)."""
        if self._lock is None:
            return
        with deferred():
            _live_claims.discard(self)
            # renamed while still locked: a process killed from here on leaves a folder that the next sweep
            # removes at once (unlocked owner file, or none under the removal name), never an ownerless claim
            trash = removal_path(self.staging)
            try:
                os.rename(self.staging, trash)
            except OSError:
                trash = self.staging
            self._lock.release()
            self._lock = None
            shutil.rmtree(trash, ignore_errors=True)
            if not self.committed:
                for folder in self._created:  # deepest first; only while empty
                    try:
                        folder.rmdir()
                    except OSError:
                        break

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()
        return False


#: The claims of this process not released yet.
_live_claims: set[RunClaim] = set()


def release_live_claims() -> int:
    """Release every claim of this process that is still held (a command line's last step, however it ends: a
    signal can arrive between a claim being taken and its holder's ``with`` or ``try`` — it must not leave the
    staging folder behind).  Returns how many were released."""
    claims = list(_live_claims)
    for claim in claims:
        claim.release()
    return len(claims)


#: The words of the error when another run holds a name.
BUSY = "another run is writing this one"


def _busy(out: Path, staging: Path) -> str:
    try:
        record = json.loads((staging / OWNER_FILE).read_text(encoding="utf-8"))
        who = f" (pid {record.get('pid')} on {record.get('host')}, started " \
              f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(record.get('started_unix_s', 0)))})"
    except (OSError, ValueError, TypeError, UnicodeDecodeError, OverflowError):
        who = ""
    return f"a run folder no other run is writing: {BUSY}{who}"


def _try_claim(out: Path, replace: bool, created: list[Path]) -> RunClaim | None:
    """Create the staging folder of ``out``; None if another live run holds it."""
    staging = staging_path(out)
    for _ in range(3):
        claim = None
        try:
            with deferred():  # a signal arriving inside is raised as the block ends: the claim is released then
                try:
                    os.mkdir(staging)
                except FileExistsError:
                    pass
                else:
                    try:
                        lock = lock_new_folder(staging, run=out.name, path=str(out))
                    except BaseException:
                        shutil.rmtree(staging, ignore_errors=True)
                        raise
                    claim = RunClaim(out, staging, lock, replace, created)
        except BaseException:
            if claim is not None:
                claim.release()
            raise
        if claim is not None:
            return claim
        if not remove_if_abandoned(staging, restore=_restore_previous):
            return None
    return None  # pragma: no cover - lost three races for an abandoned claim


def claim_run_dir(out_dir, *, if_exists: str = "stop", taken=None) -> RunClaim:
    """Claim run folder ``out_dir`` for this process (see module doc).

    ``if_exists``: "stop" refuses an existing folder, "replace" replaces a previous run of this tool (nothing
    else), "new" takes the next free name (``<name>_2`` …; ``taken(path)`` may declare more names taken).
    Raises ConfigError (field ``out``) naming the folder; nothing is left behind then."""
    mode = str(if_exists).lower()
    if mode not in ("stop", "replace", "new"):
        raise ConfigError("if_exists", if_exists, "one of stop, replace, new")
    base = check_run_dir(out_dir, overwrite=mode == "replace") if mode != "new" else _checked_name(out_dir)
    created = []
    parent = base.parent
    while not parent.exists():
        created.append(parent)
        parent = parent.parent
    base.parent.mkdir(parents=True, exist_ok=True)
    claim = None
    try:
        remove_abandoned_staging(base.parent)
        if mode != "new":
            claim = _try_claim(base, mode == "replace", created)
            if claim is None:
                _refuse(base, _busy(base, staging_path(base)))
            if base.exists() or base.is_symlink():  # re-checked under the claim
                check_run_dir(base, overwrite=mode == "replace")
            return claim
        for cand in _numbered(base):
            if cand.exists() or cand.is_symlink() or (taken is not None and taken(cand)):
                continue
            claim = _try_claim(cand, False, created)
            if claim is None:
                continue
            if cand.exists() or cand.is_symlink():  # appeared before the claim
                claim.release()
                continue
            return claim
    except BaseException:  # (a signal between taking a claim and returning it included)
        if claim is not None:
            claim.release()
        for folder in created:
            try:
                folder.rmdir()
            except OSError:
                break
        raise

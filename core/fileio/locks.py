"""Folders held by a running process: an owner file locked for the folder's life, so that what a killed process
left (SIGKILL cannot be caught) is recognised by the next one and removed — and only that.

The owner file (``ladar-owner.json``: pid, host, process start time, what the folder is for) is created in a
new folder and locked (``flock``: the kernel releases it when the process ends, however it ends).  A folder is
*abandoned* when its owner file's lock is free — or, on a file system without locks, when it was written on
this host by a pid that is no longer running (or now belongs to a process started later).  A folder of this
tool without an owner file is abandoned once it is older than :data:`OWNERLESS_GRACE_S` (its creator died
between ``mkdir`` and writing the owner file) — at once if the owner file it was writing (named after its host and
pid) shows a process of this host that is no longer running.  Standard library only (``scripts/blender_env.py`` uses it
before Blender starts).
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import socket
import time
from pathlib import Path

OWNER_FILE = "ladar-owner.json"
#: A folder without an owner file older than this is abandoned.
OWNERLESS_GRACE_S = 60.0

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None
try:  # Windows
    import msvcrt
except ImportError:
    msvcrt = None


# ------------------------------------------------------------------------------------------------------------
# Owner files: a folder held by a running process
# ------------------------------------------------------------------------------------------------------------
def _process_start(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (Linux), to tell a reused pid; None elsewhere."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2:].split()[19]
    except (OSError, ValueError, IndexError):
        return None


def _try_lock(fd: int) -> bool | None:
    """Lock ``fd`` exclusively without waiting: True locked, False held by another process, None no locking."""
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        elif msvcrt is not None:  # pragma: no cover - Windows
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        else:  # pragma: no cover
            return None
        return True
    except BlockingIOError:
        return False
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EAGAIN, errno.EDEADLK):
            return False
        return None  # ENOLCK, EOPNOTSUPP …: the file system has no locks


class FolderLock:
    """The owner file of a folder, locked by this process until :meth:`release` (or the process ends)."""

    def __init__(self, folder: Path, **info):
        self.folder = Path(folder)
        # written and locked under a temporary name, then renamed: the owner file appears whole and locked (a
        # process killed before the rename leaves an owner-less folder, removed after OWNERLESS_GRACE_S)
        path = self.folder / OWNER_FILE
        partial = self.folder / partial_owner_name(os.getpid())
        self.fd = os.open(partial, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            self.locked = _try_lock(self.fd)
            record = {"tool": "ladar-simulator", "pid": os.getpid(), "host": socket.gethostname(),
                      "process_start": _process_start(os.getpid()), "started_unix_s": time.time(), **info}
            try:
                os.write(self.fd, json.dumps(record).encode("utf-8"))
            except OSError as exc:  # a full disk: named, as every writer's failure (core.fileio.run_folder.naming)
                raise OSError(exc.errno, exc.strerror, str(path)) from None
            os.rename(partial, path)
        except BaseException:
            os.close(self.fd)
            self.fd = None
            raise

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def _host_tag() -> str:
    return hashlib.sha256(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:12]


def partial_owner_name(pid: int) -> str:
    """The name an owner file is written under before it takes its own: it says which host and pid write it, so
    a folder whose creator died before the rename is known to be abandoned without waiting."""
    return f".{OWNER_FILE}.{_host_tag()}.{pid}.partial"


def _partial_owner_gone(folder: Path) -> bool:
    """``folder`` holds an owner file being written by a process of this host that is no longer running."""
    if os.name != "posix":  # os.kill(pid, 0) is not a liveness probe on Windows (signal 0 is CTRL_C_EVENT there)
        return False
    head, tail = f".{OWNER_FILE}.{_host_tag()}.", ".partial"
    try:
        names = [n for n in os.listdir(folder) if n.startswith(head) and n.endswith(tail)]
    except OSError:
        return False
    for name in names:
        try:
            os.kill(int(name[len(head):-len(tail)]), 0)
        except ProcessLookupError:
            return True
        except (ValueError, OSError):
            continue
    return False


def _pid_alive(record: dict) -> bool:
    """From an owner record alone: could that process still be running?  (Another host: assume yes.)"""
    if record.get("host") != socket.gethostname():
        return True
    try:
        pid = int(record["pid"])
        os.kill(pid, 0)
    except (KeyError, TypeError, ValueError):
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    except OSError:  # pragma: no cover
        return True
    start = record.get("process_start")
    return start is None or _process_start(pid) in (None, start)


def _abandoned(folder: Path):
    """If ``folder``'s owner is gone, return (lock fd to close or None, owner record); else None.

    The returned lock (when the file system has locks) is held, so no other process takes the same folder for
    abandoned meanwhile."""
    path = folder / OWNER_FILE
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        if REMOVING in folder.name:  # a removal cut short after the owner file went: nobody claims this name
            return None, {}
        if _partial_owner_gone(folder):  # its creator died while writing the owner file
            return None, {}
        try:
            young = time.time() - folder.stat().st_mtime < OWNERLESS_GRACE_S
        except OSError:
            return None
        return None if young else (None, {})
    except OSError:
        return None
    try:
        try:
            record = json.loads(os.read(fd, 1 << 16).decode("utf-8") or "{}")
        except (ValueError, UnicodeDecodeError):
            record = {}
        if not isinstance(record, dict) or record.get("tool") != "ladar-simulator":
            os.close(fd)
            return None  # not ours
        locked = _try_lock(fd)
        if locked is False:
            os.close(fd)
            return None
        if locked is None and _pid_alive(record):
            os.close(fd)
            return None
        try:  # the file we locked must still be the folder's owner file (not one renamed away meanwhile)
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except OSError:
            same = False
        if not same:
            os.close(fd)
            return None
        return fd, record
    except BaseException:
        os.close(fd)
        raise


REMOVING = ".removing-"


def removal_path(folder) -> Path:
    """The name ``folder`` is renamed to before it is removed: same prefix and suffix (so the sweep that finds
    ``folder`` finds it too), marked as being removed (so a removal cut short is recognised even without its
    owner file)."""
    folder = Path(folder)
    stem, dot, suffix = folder.name.rpartition(".")
    return folder.with_name(f"{stem or suffix}{REMOVING}{os.getpid()}-{time.monotonic_ns() % 10**9}"
                            + (f".{suffix}" if dot else ""))


def remove_if_abandoned(folder, restore=None) -> bool:
    """Remove ``folder`` if it holds an owner file of this tool whose process is gone.  Returns True if removed.

    ``restore(folder, record)`` runs first (with the folder still held), e.g. to put back what the dead run
    had moved into it."""
    folder = Path(folder)
    found = _abandoned(folder)
    if found is None:
        return False
    fd, record = found
    try:
        # renamed first (atomic: one remover); the new name keeps the folder's prefix and suffix, so what an
        # interrupted removal leaves is found again by the same sweep
        trash = removal_path(folder)
        try:
            if restore is not None:
                restore(folder, record)
            os.rename(folder, trash)  # atomic: only one remover
        except OSError:
            return False
        shutil.rmtree(trash, ignore_errors=True)
        return True
    finally:
        if fd is not None:
            os.close(fd)


def lock_new_folder(folder, **info) -> FolderLock:
    """Create the owner file in ``folder`` (made by this process) and hold its lock."""
    return FolderLock(Path(folder), **info)

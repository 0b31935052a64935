"""Large freed blocks kept for the next frame (Linux, glibc); standard library only.

A frame allocates its large arrays afresh and frees them at its end: the waveform cube and the receiver's counts
(100 MB on the full-physics benchmark frame), the blocks' temporaries.  glibc's malloc serves a block above its
mmap threshold (at most 32 MiB by default) with new pages from the kernel and unmaps it on free, so every frame
paid again for mapping, faulting and zeroing them: 27–41 ms of system time per full-physics benchmark frame
(11 % of its CPU), 20 ms per noise-free one.

:func:`keep_freed_blocks` (called by every frame, core.engine.frame.open_frame; it acts once per process) raises
glibc's mmap threshold to :data:`MMAP_THRESHOLD_BYTES` and its trim threshold to :data:`KEEP_BYTES`: large blocks
come from the heap and stay there when freed, and the next frame's arrays reuse them.
:func:`release_freed_blocks` (``malloc_trim``) hands the free pages back to the system; runs call it when they end
(core.run, core.sequence), so that Blender does not hold a run's memory after it.  Code that calls the systems'
``simulate_*`` directly, frame after frame, keeps up to about :data:`KEEP_BYTES` of freed memory until it calls
:func:`release_freed_blocks` itself.

Nothing is changed with other C libraries (macOS, Windows, musl) or when the environment sets
``LADAR_KEEP_FREED_MEMORY=0``.  Only where memory comes from changes, never a value.
"""
from __future__ import annotations

import ctypes
import os
import sys
import threading

#: glibc's mmap threshold while freed blocks are kept: blocks below this come from the heap ...
MMAP_THRESHOLD_BYTES = 1 << 30
#: ... and free memory at the heap's top is handed back only beyond this (glibc's trim threshold).  128 MiB holds
#: a frame's cubes (100 MB on the full-physics benchmark frame); 1 GiB held back on the 3 s survey raised its
#: peak from 0.89 to 1.01 GB, 128 MiB leaves it at 0.89 GB.
KEEP_BYTES = 128 << 20
#: mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3

_lock = threading.Lock()
_state = {"checked": False, "kept": False, "libc": None}


def _glibc():
    """The process's C library when it is glibc (it has ``mallopt`` and ``malloc_trim``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        if not all(hasattr(libc, name) for name in ("gnu_get_libc_version", "mallopt", "malloc_trim")):
            return None
    except OSError:  # pragma: no cover - a process without a dynamic C library
        return None
    return libc


def keep_freed_blocks() -> bool:
    """Keep large freed blocks in the heap for the next frame (module docstring), once per process.  Returns
    whether they are kept (False: not glibc, ``LADAR_KEEP_FREED_MEMORY=0``, or mallopt refused)."""
    if _state["checked"]:
        return _state["kept"]
    with _lock:
        if not _state["checked"]:
            libc = None if os.environ.get("LADAR_KEEP_FREED_MEMORY", "1") == "0" else _glibc()
            kept = False
            if libc is not None:  # (the trim threshold first: with the mmap threshold alone freed blocks go back)
                kept = bool(libc.mallopt(_M_TRIM_THRESHOLD, KEEP_BYTES)) and \
                    bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
            _state["kept"], _state["libc"], _state["checked"] = kept, libc if kept else None, True
    return _state["kept"]


def release_freed_blocks() -> None:
    """Hand the heap's free pages back to the system (``malloc_trim(0)``) when freed blocks are kept."""
    if _state["kept"]:
        _state["libc"].malloc_trim(0)

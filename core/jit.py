"""The one home of the numba import: compiled kernels of the signal chain (waveforms, echo detection).

Kernels are ``@kernel`` functions (numba ``njit(nogil=True, cache=True)``): they release the GIL, so the
pipeline's thread pool runs them in parallel, and their machine code is cached on disk after the first run.
The cache goes to a writable per-user folder — never into the package, which an installed Blender extension
may not be allowed to write to:

* ``$NUMBA_CACHE_DIR`` if the user set it;
* Linux: ``$XDG_CACHE_HOME/ladar_simulator/numba`` (default ``~/.cache/...``); macOS:
  ``~/Library/Caches/ladar_simulator/numba``; Windows: ``%LOCALAPPDATA%\\ladar_simulator\\numba``.

The first run of a fresh installation compiles every kernel it calls (a few seconds, once per user and
version: docs/performance.md); later runs load them from the cache.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path


def user_cache_dir() -> Path:
    """The per-user folder of compiled kernels (not created here)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    home = Path.home()
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or home / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = home / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or home / ".cache")
    return base / "ladar_simulator" / "numba"


CACHE_DIR = user_cache_dir()
if "numba" not in sys.modules:
    os.environ.setdefault("NUMBA_CACHE_DIR", str(CACHE_DIR))

import numba  # noqa: E402

if not numba.config.CACHE_DIR:  # numba was imported before us (another add-on): point its cache locator here
    numba.config.CACHE_DIR = str(CACHE_DIR)


def kernel(fn):
    """Compile ``fn`` in nopython mode, releasing the GIL, cached per user."""
    return numba.njit(nogil=True, cache=True)(fn)

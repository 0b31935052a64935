"""The one home of the numba import: compiled kernels of the signal chain (waveforms, echo detection).

Kernels are ``@kernel`` functions (numba ``njit(nogil=True, cache=True)``): they release the GIL, so the
pipeline's thread pool runs them in parallel, and their machine code is cached on disk after the first run.
The cache goes to a writable per-user folder — never into the package, which an installed Blender extension
may not be allowed to write to:

* ``$NUMBA_CACHE_DIR`` if the user set it (a subfolder of it, below);
* Linux: ``$XDG_CACHE_HOME/ladar_simulator/numba`` (default ``~/.cache/...``); macOS:
  ``~/Library/Caches/ladar_simulator/numba``; Windows: ``%LOCALAPPDATA%\\ladar_simulator\\numba``.

The cache lives in a subfolder named after a digest of the package's source (every ``.py`` file of core/)
and the numba version.  numba checks a cached kernel only against its own file's time stamp, but a kernel
holds the kernels and module constants (tables, physical constants) it calls from other files as they were when
it was compiled: without the digest, a change to ``physics/laser.py`` alone (a ``git pull``, a hand edit) would
leave ``physics/waveform.py``'s cached kernels computing with the old tables.  Digest folders not used for
:data:`STALE_CACHE_DAYS` are removed at import.

The first run of a fresh installation compiles every kernel it calls (a few seconds, once per user and
version: docs/performance.md); later runs load them from the cache.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


def source_digest() -> str:
    """16 hex digits of SHA-256 over the numba version and every .py file of the core package (path and bytes)."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    try:
        h.update(version("numba").encode())
    except PackageNotFoundError:  # pragma: no cover - numba imported from a path without metadata
        pass
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode("utf-8", "surrogateescape") + b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def user_cache_dir() -> Path:
    """The per-user folder of compiled kernels, without the source digest (not created here)."""
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


#: Cache folders of other sources (other versions, older edits) unused this long are removed.
STALE_CACHE_DAYS = 30


def prune_stale_caches(cache_dir: Path, max_age_days: float = STALE_CACHE_DAYS) -> list[Path]:
    """Mark ``cache_dir`` as used now and remove the sibling digest folders (16 hex digits) not used for
    ``max_age_days``; never anything else.  Errors are ignored (a cache is never worth failing a run)."""
    removed = []
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        os.utime(cache_dir)
        limit = time.time() - max_age_days * 86400.0
        for entry in os.scandir(cache_dir.parent):
            name = entry.name
            if (entry.is_dir(follow_symlinks=False) and len(name) == 16 and name != cache_dir.name
                    and all(c in "0123456789abcdef" for c in name) and entry.stat().st_mtime < limit):
                shutil.rmtree(entry.path, ignore_errors=True)
                removed.append(Path(entry.path))
    except OSError:
        pass
    return removed


_DIGEST = source_digest()
_BASE = user_cache_dir()
#: This source's kernel cache (a child process inherits NUMBA_CACHE_DIR already ending in the digest).
CACHE_DIR = _BASE if _BASE.name == _DIGEST else _BASE / _DIGEST
prune_stale_caches(CACHE_DIR)
if "numba" not in sys.modules:
    os.environ.setdefault("NUMBA_CACHE_DIR", str(CACHE_DIR))

import numba  # noqa: E402
import numba.extending  # noqa: E402

if not numba.config.CACHE_DIR:  # numba was imported before us (another add-on): point its cache locator here
    numba.config.CACHE_DIR = str(CACHE_DIR)


def kernel(fn=None, *, inline: bool = False):
    """Compile ``fn`` in nopython mode, releasing the GIL, cached per user.

    ``@kernel(inline=True)``: a helper that takes arrays and is called once per element of a loop, inlined
    into its callers' code (numba ``inline="always"``): a call that is not inlined counts references to each of
    its array arguments, a few ns per call and array (20 ns a ray for a material look-up)."""
    if fn is None:
        return lambda f: kernel(f, inline=inline)
    return numba.njit(nogil=True, cache=True, inline="always" if inline else "never")(fn)


#: numba's ``intrinsic`` decorator, for the kernels written in LLVM IR (:func:`fma`; the 4-lane binning in
#: core/physics/laser.py): the other modules take it from here, numba's one home.
intrinsic = numba.extending.intrinsic
#: numba's types, for the signatures of those kernels
nbtypes = numba.types


@intrinsic
def fma(typingctx, a, b, c):
    """a·b + c rounded once (LLVM's fma: one instruction on CPUs with FMA, exact in software elsewhere), for
    kernels: float64 only.  Where the product a·b is exact in float64 (e.g. two numbers of ≤ 26 significant
    bits each) it equals ``a * b + c`` bit for bit, in half the instructions."""
    from llvmlite import ir

    f64 = numba.types.float64
    if not (a == f64 and b == f64 and c == f64):
        return None

    def codegen(context, builder, signature, args):
        ty = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [ty], fnty=ir.FunctionType(ty, [ty, ty, ty]))
        return builder.call(fn, args)

    return f64(f64, f64, f64), codegen

"""The one home of the numba import: compiled kernels of the signal chain (waveforms, echo detection).

Kernels are ``@kernel`` functions (numba ``njit(nogil=True)``): they release the GIL, so the pipeline's thread
pool runs them in parallel, and their machine code is kept on disk after the first run by this module's own
cache (:class:`KernelCache`), which numba's ``cache=True`` would not do well for a Blender extension:

* **Found again wherever the same source is installed.**  numba files a cached kernel under the absolute path of
  its source folder and checks it against the file's time stamp, so a new install folder (every run of
  ``scripts/ladar_run.py`` installs the extension into a fresh temporary Blender user folder; a sweep worker
  receives the core in a new folder) compiled every kernel again.  Here the cache folder is named after a
  digest of the package's source (every ``.py`` file of core/, path within core/ and bytes) and the numba
  version, and inside it ``ladar_kernels`` and the file's folder *within* core/ — never by absolute path, and
  not by the core's import name either (``core`` in a checkout, ``bl_ext.<repo>.ladar_simulator.core`` as an
  extension, ``ladar_core_<digest>`` on a sweep worker): a compiled kernel refers to the modules it was compiled
  in by name (numba's function descriptor, its symbol names, the environment that holds its module's globals),
  so every kernel is compiled as if its module were ``ladar_kernels.<path within core>`` (numba's function
  identity and descriptor name it so; the descriptor's module look-up and this cache's pickles map the name back
  to the modules of the copy that runs), and one compiled kernel serves every import name of the same source.
  The first copy of the core imported in a process owns that name (:data:`SHARED`); a second copy in the same
  process (a benchmark's ``core_base``, a test's copy) keeps its import name for numba and files its kernels
  under CACHE_DIR / its import name (:data:`KERNEL_DIR`), as every copy did before: two copies never define the
  same symbols in numba's one JIT, and no copy's kernels run on another copy's module globals.  An entry's file
  name is the kernel, its line and a digest of numba's key (signature, CPU name and features, bytecode), so
  the CPU decides the machine code as before (``NUMBA_CPU_NAME`` included).  A change to any core file gives a
  new digest: a kernel holds the kernels and module constants (tables) it calls from other files as they were
  when compiled, so editing ``physics/laser.py`` alone must not leave ``physics/waveform.py``'s cached kernels
  on the old tables.
* **Per user, never in the package**: ``$LADAR_KERNEL_CACHE`` if set, else ``$NUMBA_CACHE_DIR/ladar_simulator``
  if the user set ``NUMBA_CACHE_DIR``, else ``$XDG_CACHE_HOME/ladar_simulator/numba`` (default ``~/.cache``) on
  Linux, ``~/Library/Caches/ladar_simulator/numba`` on macOS, ``%LOCALAPPDATA%\\ladar_simulator\\numba`` on
  Windows.  If no folder there is writable the kernels are compiled and not kept (one line says so); nothing is
  ever written into the installed package.  numba's own cache setting (``NUMBA_CACHE_DIR``) is not changed for
  the rest of the process: another add-on's numba caches stay where they were.
* **Safe**: an entry is written to a temporary file and renamed into place (a run killed while writing leaves no
  half entry; two runs compiling at once each write whole entries, the last one wins); each entry carries a
  SHA-256 of its contents and the key it was compiled for, checked before it is unpickled, so a truncated,
  zeroed, random or bit-flipped file, or an entry another process wrote under the same name, costs a compile
  (one line names it), never a failed run or a crash; a full disk or an unwritable folder while saving costs
  only the saving.
* **Bounded**: the digest folders are marked as this cache's own (a ``LADAR_KERNEL_CACHE`` file in each); at
  import the folders so marked and unused for :data:`STALE_CACHE_DAYS`, and all but the
  :data:`KEEP_CACHE_FOLDERS` most recently used, are removed — never a folder without the mark.

The first run of a fresh installation compiles the kernels it calls (seconds: docs/performance.md; ``ladar
warm-up`` — core/warmup.py — or the sensor panel's *Compile Kernels Now* does it ahead, with progress); later
runs load them from the cache.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib
import io
import os
import pickle
import shutil
import sys
import threading
import time
import uuid
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

#: The core package's folder (this file's): kernels of files below it are cached here.
ROOT = Path(__file__).resolve().parent
#: The core package's import name (``core``, ``bl_ext.user_default.ladar_simulator.core``, ``ladar_core_…``).
IMPORT_NAME = __name__.rpartition(".")[0] or "core"
#: Marks a folder as this cache's own: only folders holding it are ever pruned.
MARK = "LADAR_KERNEL_CACHE"


def source_digest() -> str:
    """16 hex digits of SHA-256 over the numba version and every .py file of the core package (path and bytes)."""
    h = hashlib.sha256()
    try:
        h.update(version("numba").encode())
    except PackageNotFoundError:  # pragma: no cover - numba imported from a path without metadata
        pass
    for path in sorted(ROOT.rglob("*.py")):
        h.update(path.relative_to(ROOT).as_posix().encode("utf-8", "surrogateescape") + b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def user_cache_dir() -> Path:
    """The per-user folder of compiled kernels, without the source digest (not created here)."""
    if os.environ.get("LADAR_KERNEL_CACHE"):
        return Path(os.environ["LADAR_KERNEL_CACHE"])
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"]) / "ladar_simulator"
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
#: At most this many source digests are kept (a developer's every edit is a new digest).
KEEP_CACHE_FOLDERS = 8


def _is_digest(name: str) -> bool:
    return len(name) == 16 and all(c in "0123456789abcdef" for c in name)


def prune_stale_caches(cache_dir: Path, max_age_days: float = STALE_CACHE_DAYS,
                       keep: int = KEEP_CACHE_FOLDERS) -> list[Path]:
    """Mark ``cache_dir`` as ours and used now; remove the sibling digest folders (16 hex digits) that hold
    the mark and were not used for ``max_age_days``, or are beyond the ``keep`` most recently used; never
    anything else.  Errors are ignored (a cache is never worth failing a run)."""
    removed = []
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        mark = cache_dir / MARK
        if not mark.exists():
            mark.write_text("compiled kernels of the ladar simulator; safe to delete\n")
        os.utime(cache_dir)
        limit = time.time() - max_age_days * 86400.0
        ours = []
        for entry in os.scandir(cache_dir.parent):
            if (entry.is_dir(follow_symlinks=False) and _is_digest(entry.name) and entry.name != cache_dir.name
                    and os.path.isfile(os.path.join(entry.path, MARK))):
                ours.append((entry.stat().st_mtime, entry.path))
        ours.sort(reverse=True)
        for rank, (mtime, path) in enumerate(ours):
            if mtime < limit or rank >= keep - 1:
                shutil.rmtree(path, ignore_errors=True)
                removed.append(Path(path))
    except OSError:
        pass
    return removed


_DIGEST = source_digest()
#: This source's kernel cache.
CACHE_DIR = user_cache_dir() / _DIGEST
prune_stale_caches(CACHE_DIR)

import numba  # noqa: E402
import numba.extending  # noqa: E402
from numba.core import caching as _caching  # noqa: E402
from numba.core import funcdesc as _funcdesc  # noqa: E402
from numba.core.bytecode import FunctionIdentity as _FunctionIdentity  # noqa: E402
from numba.core.environment import Environment as _Environment  # noqa: E402
from numba.core.serialize import NumbaPickler as _NumbaPickler  # noqa: E402

from .process import deferred as _deferred  # noqa: E402

#: The module name every kernel of the core is compiled under, whatever the core's import name: its modules are
#: ``ladar_kernels.<path within core>`` to numba (symbol names, environments), so one compiled kernel serves
#: ``core``, ``bl_ext.<repo>.ladar_simulator.core`` and ``ladar_core_<digest>`` alike (module docstring).
CANONICAL = "ladar_kernels"


def _claim() -> bool:
    """Make this copy of the core the process's owner of :data:`CANONICAL` if no copy is: numba's function
    identities and descriptors then name this copy's modules canonically (every kernel's symbols, environment
    and module look-up).  A later copy (another import name, another source, a re-import) stays under its own
    import name, as each copy did before: two copies in numba's one JIT never define the same symbols, and no
    copy's kernels see another copy's module globals."""
    info = _funcdesc.FunctionDescriptor._get_function_info.__func__
    me = sys.modules[__name__]
    owner = getattr(info, "ladar_owner", None)
    if owner is me:  # this module re-executed (importlib.reload): still the owner
        me._canonical, me._real = info.ladar_maps
        return True
    if owner is not None:
        return False
    prefix = IMPORT_NAME + "."

    def canonical(modname):
        if modname == IMPORT_NAME or (modname and modname.startswith(prefix)):
            return CANONICAL + modname[len(IMPORT_NAME):]
        return None

    def real(modname):
        if modname == CANONICAL or modname.startswith(CANONICAL + "."):
            return IMPORT_NAME + modname[len(CANONICAL):]
        return None

    from_function = _FunctionIdentity.from_function.__func__
    lookup_module = _funcdesc.FunctionDescriptor.lookup_module

    def _from_function(cls, pyfunc):
        self = from_function(cls, pyfunc)
        name = canonical(self.modname)
        if name is not None:
            self.modname = name  # a recursive kernel's calls are named from this (numba typeinfer)
        return self

    def _get_function_info(cls, func_ir):
        qualname, unique_name, modname, doc, args, kws, global_dict = info(cls, func_ir)
        name = canonical(modname)
        return qualname, unique_name, modname if name is None else name, doc, args, kws, global_dict

    def _lookup_module(self):
        name = real(self.modname)
        if name is None:
            return lookup_module(self)
        return sys.modules.get(name) or importlib.import_module(name)

    _get_function_info.ladar_owner = me
    _get_function_info.ladar_maps = (canonical, real)
    _FunctionIdentity.from_function = classmethod(_from_function)
    _funcdesc.FunctionDescriptor.lookup_module = _lookup_module
    _funcdesc.FunctionDescriptor._get_function_info = classmethod(_get_function_info)
    me._canonical, me._real = canonical, real
    return True


def _canonical(modname):  # replaced by _claim in the owning copy
    return None


def _real(modname):  # replaced by _claim in the owning copy
    return None


#: This copy of the core owns :data:`CANONICAL` in this process (the first copy imported does).
SHARED = _claim()
#: The folder of this copy's kernels: CACHE_DIR / ``ladar_kernels`` (shared by every import name of the source),
#: or CACHE_DIR / import name for a second copy of the core in one process.
KERNEL_DIR = CACHE_DIR / (CANONICAL if SHARED else IMPORT_NAME)

#: What happened to the cache in this process (for the run's metadata and the tests): entries loaded,
#: compiled and saved, and the notes printed.
CACHE_STATS = {"loaded": 0, "compiled": 0, "saved": 0, "rejected": 0, "unsaved": 0, "seconds": 0.0}
#: The kernels (and signatures) this process compiled because the cache did not hold them.
COMPILED: list[str] = []
_notes_lock = threading.Lock()
_noted: set[str] = set()


def _note(kind: str, text: str) -> None:
    """One line on stderr per kind of cache problem and process (a cache problem never fails a run)."""
    with _notes_lock:
        if kind in _noted:
            return
        _noted.add(kind)
    print(f"ladar: note: {text}", file=sys.stderr, flush=True)


class _Locator(_caching._CacheLocator):
    """Files a kernel of core/ under :data:`KERNEL_DIR` / its folder within core/ (module docstring)."""

    def __init__(self, py_func, py_file):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        rel = Path(py_file).resolve().parent.relative_to(ROOT).as_posix()
        self._cache_path = str(KERNEL_DIR / rel) if rel != "." else str(KERNEL_DIR)

    def ensure_cache_path(self):
        os.makedirs(self._cache_path, exist_ok=True)

    def get_cache_path(self):
        return self._cache_path

    def get_source_stamp(self):
        return _DIGEST

    def get_disambiguator(self):
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func, py_file):
        try:
            Path(py_file).resolve().relative_to(ROOT)
        except ValueError:
            return None
        return cls(py_func, py_file)


class _Impl(_caching.CompileResultCacheImpl):
    _locator_classes = [_Locator]


_MAGIC = b"LADARNB1"


class _Pickler(_NumbaPickler):
    """numba's pickler, naming this copy's modules canonically: an environment (a kernel's module globals and
    constants) and a module-level class or function of the core are kept as (canonical module, name) and found
    again in the loading copy's modules (:class:`_Unpickler`), never by the import name that compiled them."""

    def persistent_id(self, obj):
        if isinstance(obj, _Environment):
            name = _canonical(obj.globals.get("__name__"))
            if name is not None:
                return ("env", name, list(obj.consts), obj.env_name)
        elif isinstance(obj, type) or callable(obj):
            name = _canonical(getattr(obj, "__module__", None))
            qualname = getattr(obj, "__qualname__", None)
            if name is not None and isinstance(qualname, str) and _resolve(_real(name), qualname) is obj:
                return ("ref", name, qualname)
        return None


def _resolve(modname, qualname):
    obj = sys.modules.get(modname) or importlib.import_module(modname)
    for part in qualname.split("."):
        obj = getattr(obj, part, None)
    return obj


class _Unpickler(pickle.Unpickler):
    def persistent_load(self, pid):
        kind, name = pid[0], _real(pid[1])
        if name is None:  # an entry of the canonical folder in a copy that does not own the name: never filed so
            raise _Damaged(f"an entry naming {pid[1]} in a copy that does not own {CANONICAL}")
        if kind == "ref":
            obj = _resolve(name, pid[2])
            if obj is None:
                raise _Damaged(f"{pid[1]}.{pid[2]} not found in {name}")
            return obj
        if kind == "env":
            consts, env_name = pid[2], pid[3]
            env = _Environment._memo.get(env_name)
            if env is None:  # as numba's environment._rebuild_env, with the module of this copy
                module = sys.modules.get(name) or importlib.import_module(name)
                env = _Environment(module.__dict__)
                env.consts[:] = consts
                env.env_name = env_name
                _Environment._memo[env_name] = env
            return env
        raise pickle.UnpicklingError(f"unknown persistent id {kind!r}")


def _dumps(obj) -> bytes:
    with io.BytesIO() as buf:
        _Pickler(buf, protocol=4).dump(obj)
        return buf.getvalue()


class _EntryFiles:
    """One file per kernel and key: ``MAGIC | SHA-256 of the body | body``, the body a pickle of (source
    digest, key text, numba's payload).  Written to a temporary file and renamed into place."""

    def __init__(self, cache_path, filename_base):
        self._cache_path = cache_path
        self._base = filename_base

    def _path(self, key) -> str:
        h = hashlib.sha256(repr(key).encode()).hexdigest()[:16]
        return os.path.join(self._cache_path, f"{self._base}.{h}.nbc")

    def load(self, key):
        path = self._path(key)
        try:
            with open(path, "rb") as f:
                blob = f.read()
        except OSError:  # no entry, or no readable cache folder: compiled (and saving says why it cannot keep it)
            return None
        body = blob[len(_MAGIC) + 32:]
        if blob[:len(_MAGIC)] != _MAGIC or hashlib.sha256(body).digest() != blob[len(_MAGIC):len(_MAGIC) + 32]:
            raise _Damaged(f"{os.path.basename(path)}: checksum mismatch")
        digest, key_text, payload = _Unpickler(io.BytesIO(body)).load()
        if digest != _DIGEST or key_text != repr(key):
            raise _Damaged(f"{os.path.basename(path)}: an entry of another key")
        return payload

    def save(self, key, payload):
        body = _dumps((_DIGEST, repr(key), payload))
        path = self._path(key)
        tmp = f"{path}.tmp.{uuid.uuid4().hex[:12]}"
        try:
            with open(tmp, "wb") as f:
                f.write(_MAGIC + hashlib.sha256(body).digest() + body)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    def flush(self):
        pass


class _Damaged(Exception):
    pass


_tls = threading.local()
_stats_lock = threading.Lock()
_active = [0, 0.0]  # threads inside a kernel load or compile, and when the first of them entered


def _count(key: str, n: float = 1) -> None:
    with _stats_lock:
        CACHE_STATS[key] += n


def cpu_key() -> str:
    """12 hex digits naming the machine code's target: numba's CPU name and features (``NUMBA_CPU_NAME``)."""
    from numba.core.registry import cpu_target

    magic = cpu_target.target_context.codegen().magic_tuple()
    return hashlib.sha256(repr(magic).encode()).hexdigest()[:12]


def kernel_seconds() -> float:
    """Seconds this thread has spent loading and compiling kernels so far (:func:`stage_clock`)."""
    return getattr(_tls, "seconds", 0.0)


def stage_clock() -> float:
    """``time.perf_counter()`` less this thread's kernel loading and compiling so far: the clock of the stage
    times, which therefore exclude compile and load time (reported apart: :func:`kernel_report`)."""
    return time.perf_counter() - getattr(_tls, "seconds", 0.0)


def kernel_report(before: dict | None = None) -> dict:
    """Kernels loaded from the cache, compiled, and the wall seconds during which any thread loaded or compiled
    one, since ``before`` (an earlier report) or since the process started."""
    with _stats_lock:
        now = {"loaded": CACHE_STATS["loaded"], "compiled": CACHE_STATS["compiled"],
               "load_and_compile_s": CACHE_STATS["seconds"]}
    if before:
        now = {k: v - before.get(k, 0) for k, v in now.items()}
    return now


def _timed(compile_method):
    """A dispatcher's ``compile`` timed per thread (the outermost call: a kernel's callees compile inside it),
    and not cut by a signal: SIGINT/SIGTERM/SIGHUP arriving while the main thread loads or compiles a kernel is
    raised when the load or compile ends (core.process.deferred).  Inside, llvmlite calls Python back from C
    (``ExecutionEngine._raw_object_cache_notify``); an exception raised there by the signal handler is printed
    and dropped: the signal was lost and the kernel's library left without machine code ("RuntimeError: no
    compiled object yet for <Library ...>" at its next use, issue 31)."""

    def compile(sig):
        if getattr(_tls, "depth", 0):
            return compile_method(sig)
        with _deferred():
            return _outermost(sig)

    def _outermost(sig):
        _tls.depth = 1
        t0 = time.perf_counter()
        with _stats_lock:
            _active[0] += 1
            if _active[0] == 1:
                _active[1] = t0
        try:
            return compile_method(sig)
        finally:
            _tls.depth = 0
            t1 = time.perf_counter()
            _tls.seconds = getattr(_tls, "seconds", 0.0) + (t1 - t0)
            with _stats_lock:  # wall time during which any thread loads or compiles (they wait on numba's lock)
                _active[0] -= 1
                if _active[0] == 0:
                    CACHE_STATS["seconds"] += t1 - _active[1]

    return compile


class KernelCache(_caching.FunctionCache):
    """numba's per-function cache with this module's locator and entry files (module docstring)."""

    _impl_class = _Impl

    def __init__(self, py_func):
        super().__init__(py_func)
        self._cache_file = _EntryFiles(self._cache_path, self._impl.filename_base)

    def load_overload(self, sig, target_context):
        try:
            data = super().load_overload(sig, target_context)
        except Exception as exc:  # damaged, truncated, foreign: compile instead
            _count("rejected")
            _count("compiled")
            _note("damaged", f"compiled-kernel cache entry unusable ({exc.__class__.__name__}: {exc}); "
                             f"compiling it again ({self._cache_path})")
            return None
        _count("loaded" if data is not None else "compiled")
        if data is None:
            with _stats_lock:
                COMPILED.append(f"{self._py_func.__module__.rpartition('.')[2]}.{self._py_func.__qualname__}{sig}")
        return data

    def save_overload(self, sig, data):
        try:
            self._impl.locator.ensure_cache_path()
            super().save_overload(sig, data)
            _count("saved")
        except Exception as exc:  # full disk, unwritable folder: the kernel runs, it is only not kept
            _count("unsaved")
            _note("unsaved", f"compiled kernels not kept ({exc.__class__.__name__}: {exc}); the next run "
                             f"compiles them again")


def kernel(fn=None, *, inline: bool = False):
    """Compile ``fn`` in nopython mode, releasing the GIL, kept in the per-user cache (:class:`KernelCache`).

    ``@kernel(inline=True)``: a helper that takes arrays and is called once per element of a loop, inlined
    into its callers' code (numba ``inline="always"``): a call that is not inlined counts references to each of
    its array arguments, a few ns per call and array (20 ns a ray for a material look-up)."""
    if fn is None:
        return lambda f: kernel(f, inline=inline)
    dispatcher = numba.njit(nogil=True, inline="always" if inline else "never")(fn)
    try:
        dispatcher._cache = KernelCache(dispatcher.py_func)
    except RuntimeError:  # numba's "no locator available": a kernel outside core/ (a test's own) is not kept
        pass
    dispatcher.compile = _timed(dispatcher.compile)
    return dispatcher


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

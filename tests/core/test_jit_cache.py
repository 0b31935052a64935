"""core/jit.py: the compiled kernels' cache goes to a writable per-user folder, never into the package (an
installed Blender extension), whether numba is imported by us first or was imported before (another add-on); it
is found again whatever folder the same source is installed in; a damaged, foreign or unwritable cache costs a
compile (one line), never a failed run; only its own folders are pruned."""
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
#: the variables that choose the cache folder: unset so that each test's HOME decides
DROP = ("NUMBA_CACHE_DIR", "LADAR_KERNEL_CACHE", "XDG_CACHE_HOME", "LOCALAPPDATA")

RUN = """
import sys
{pre}
sys.path.insert(0, {pkg!r})
import numpy as np
from core.physics.detection.peaks import _compact, interpolate_at
import core.jit
assert interpolate_at(1.0, 3.0, 1.0, 1) == (0.0, 3.0)  # a symmetric peak: no shift
cand = np.array([4, 7, 9])
assert _compact(cand, np.array([False, True, True]), 3) == 2 and cand[:2].tolist() == [7, 9]
print(core.jit.CACHE_DIR)
"""


@pytest.mark.parametrize("numba_first", [False, True])
def test_kernel_cache_goes_to_the_user_folder_not_the_package(tmp_path, numba_first):
    pkg = tmp_path / "extension"
    shutil.copytree(REPO / "core", pkg / "core", ignore=shutil.ignore_patterns("__pycache__"))
    for p in pkg.rglob("*"):  # a read-only install (root ignores the bits: the file check below decides)
        p.chmod(p.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    home = tmp_path / "home"
    env = {k: v for k, v in os.environ.items() if k not in DROP}
    env.update(HOME=str(home), USERPROFILE=str(home), PYTHONDONTWRITEBYTECODE="1")
    code = RUN.format(pre="import numba" if numba_first else "", pkg=str(pkg))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    cache = Path(out.stdout.strip().splitlines()[-1])
    if sys.platform.startswith("linux"):
        assert cache.parent == home / ".cache" / "ladar_simulator" / "numba"
    assert home in cache.parents
    assert list(cache.rglob("*.nbc")), "no kernel cached in the per-user folder"
    assert not [p for p in pkg.rglob("*") if p.suffix in (".nbi", ".nbc")], "kernel cache written into the package"
    for p in pkg.rglob("*"):
        p.chmod(p.stat().st_mode | stat.S_IWUSR)


def _cache_dir_of(pkg: Path, home: Path, numba_cache_dir=None) -> Path:
    env = {k: v for k, v in os.environ.items() if k not in DROP}
    if numba_cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = str(numba_cache_dir)
    env.update(HOME=str(home), USERPROFILE=str(home), PYTHONDONTWRITEBYTECODE="1")
    code = f"import sys; sys.path.insert(0, {str(pkg)!r}); import core.jit; print(core.jit.CACHE_DIR)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=pkg)
    assert out.returncode == 0, out.stderr[-2000:]
    return Path(out.stdout.strip().splitlines()[-1])


def test_a_change_to_any_core_file_gives_the_kernels_a_new_cache_folder(tmp_path):
    """numba checks a cached kernel against its own file only, while a kernel holds the kernels and tables it
    calls from other files as compiled (physics/waveform.py's binning calls physics/laser.py's tail tables):
    the cache folder is named after a digest of every core file, so editing laser.py alone cannot leave
    waveform.py's cached kernels on the old tables."""
    a, b = tmp_path / "a", tmp_path / "b"
    for pkg in (a, b):
        shutil.copytree(REPO / "core", pkg / "core", ignore=shutil.ignore_patterns("__pycache__"))
    home = tmp_path / "home"
    first, same = _cache_dir_of(a, home), _cache_dir_of(b, home)
    assert first == same and first.parent == _cache_dir_of(a, home).parent  # same sources: same folder
    laser = b / "core" / "physics" / "laser.py"
    laser.write_text(laser.read_text() + "\n# edited\n")
    changed = _cache_dir_of(b, home)
    assert changed.parent == first.parent and changed.name != first.name and len(changed.name) == 16
    # a user's NUMBA_CACHE_DIR holds ours in a folder of its own
    assert _cache_dir_of(a, home, numba_cache_dir=tmp_path / "mine") == tmp_path / "mine" / "ladar_simulator" / first.name


def test_only_our_stale_or_surplus_digest_folders_are_pruned(tmp_path):
    """Digest folders holding the cache's mark and unused for 30 days, or beyond the 8 most recently used, are
    removed; a folder without the mark (another program's, in a shared NUMBA_CACHE_DIR) never is."""
    import time

    from core.jit import KEEP_CACHE_FOLDERS, MARK, prune_stale_caches

    parent = tmp_path / "numba"
    current, stale, fresh = parent / "0123456789abcdef", parent / "fedcba9876543210", parent / "00000000aaaaaaaa"
    foreign = parent / "1111111111111111"  # a digest-like name without our mark: never ours to remove
    other = parent / "core_1491019fea487c031e0fdc1b53f8b1f2"  # not a digest folder
    for d in (stale, fresh, other, foreign):
        (d / "x").mkdir(parents=True)
    for d in (stale, fresh):
        (d / MARK).write_text("")
    old = time.time() - 31 * 86400.0
    for d in (stale, other, foreign):
        os.utime(d, (old, old))
    assert prune_stale_caches(current) == [stale]
    assert sorted(p.name for p in parent.iterdir()) == sorted([current.name, fresh.name, other.name, foreign.name])
    assert time.time() - current.stat().st_mtime < 60  # marked as used
    assert (current / MARK).is_file()
    # a developer's many edits: only the most recently used digests stay
    now = time.time()
    made = []
    for i in range(12):
        d = parent / f"{i:016x}"
        (d / "x").mkdir(parents=True)
        (d / MARK).write_text("")
        os.utime(d, (now - 1000 + i, now - 1000 + i))
        made.append(d)
    os.utime(fresh, (now - 5000, now - 5000))
    removed = prune_stale_caches(current)
    kept = sorted(p.name for p in parent.iterdir() if (p / MARK).exists())
    assert len(kept) == KEEP_CACHE_FOLDERS and current.name in kept
    assert set(kept) == {current.name} | {d.name for d in made[-(KEEP_CACHE_FOLDERS - 1):]}
    assert fresh in removed and foreign.exists() and other.exists()


def test_fma_rounds_once_and_equals_multiply_add_where_the_product_is_exact():
    """core.jit.fma is a fused multiply-add: one rounding (0.1·10 − 1 is 2⁻⁵⁴ exactly, where the separate product
    rounds to 1 and gives 0), and where the product is exact — a sum of two halves below 2²¹ times a float32 tap,
    as the matched filter uses it — the same number as ``a * b + c``."""
    import numba
    import numpy as np

    from core.jit import fma

    @numba.njit
    def f(a, b, c):
        out = np.empty(a.shape[0])
        for i in range(a.shape[0]):
            out[i] = fma(a[i], b[i], c[i])
        return out

    assert f(np.array([0.1]), np.array([10.0]), np.array([-1.0]))[0] == 2.0 ** -54
    assert 0.1 * 10.0 - 1.0 == 0.0
    rng = np.random.default_rng(7)
    n = 100_000
    a = np.round(rng.uniform(-2 ** 23, 2 ** 23, n)) / 2  # pair sums of halves below 2²¹ in magnitude
    b = rng.standard_normal(n).astype(np.float32).astype(np.float64)  # float32 taps
    c = rng.standard_normal(n) * 10.0 ** rng.uniform(-8, 8, n)
    assert np.array_equal(f(a, b, c), a * b + c)


# --- found again from any folder; damage, races and a full disk cost a compile, never a run ---------------------

PROBE = """
import json, sys
sys.path.insert(0, {pkg!r})
import numpy as np
from core.config.settings import DetectionSettings
from core.physics.detection.peaks import detect_echoes
import core.jit
w = np.zeros((3, 64)); w[0, 5:8] = (1.0, 3.0, 1.0); w[1, 30:33] = (2.0, 5.0, 1.0); w[2, 50:53] = (1.0, 1.5, 1.2)
e = detect_echoes(w, DetectionSettings())
print(json.dumps({{"cache": str(core.jit.CACHE_DIR), "stats": core.jit.CACHE_STATS,
                  "positions": [float(x).hex() for x in e.position_bins]}}))
"""


#: The cache mechanism's probe: two small kernels of core/ (a scalar one and one on arrays), two cache entries,
#: compiled in about 1 s of CPU where PROBE's echo detection (six kernels) takes about 7 s; for the tests whose
#: point is the cache's handling of entries (damage, an unwritable folder, two writers), not which kernels a run
#: needs (test_the_same_source_in_another_folder_loads_every_kernel_and_compiles_none keeps PROBE; every kernel of
#: a whole run: tests/addon/test_fault_injection.py::
#: test_signals_while_kernels_compile_or_load_leave_nothing_and_the_cache_works).
SMALL_PROBE = """
import json, sys
sys.path.insert(0, {pkg!r})
import numpy as np
from core.physics.detection.peaks import _compact, interpolate_at
import core.jit
peaks = [interpolate_at(1.0, 3.0, 1.5, 2), interpolate_at(2.0, 5.0, 1.0, 1)]
cand = np.array([4, 7, 9, 12])
kept = _compact(cand, np.array([True, False, True, True]), 4)
assert kept == 3 and cand[:3].tolist() == [4, 9, 12]
print(json.dumps({{"cache": str(core.jit.CACHE_DIR), "stats": core.jit.CACHE_STATS,
                  "positions": [float(x).hex() for p in peaks for x in p]}}))
"""


def _probe(pkg: Path, cache: Path, *, expect_ok=True, code=PROBE):
    """Run ``code`` (a probe) on the core copy in ``pkg`` with the kernel cache in ``cache``: (report, stderr)."""
    import json

    env = {k: v for k, v in os.environ.items() if k not in DROP}
    env.update(LADAR_KERNEL_CACHE=str(cache), PYTHONDONTWRITEBYTECODE="1")
    out = subprocess.run([sys.executable, "-c", code.format(pkg=str(pkg))], capture_output=True, text=True,
                         env=env, cwd=pkg)
    assert (out.returncode == 0) == expect_ok, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1]), out.stderr


def _copy_core(dest: Path) -> Path:
    shutil.copytree(REPO / "core", dest / "core", ignore=shutil.ignore_patterns("__pycache__"))
    return dest


def test_the_same_source_in_another_folder_loads_every_kernel_and_compiles_none(tmp_path):
    """numba's own cache is filed under the source folder's absolute path and checked against the file's time
    stamp: a new install folder compiled every kernel again.  Ours is keyed on the source's digest."""
    cache = tmp_path / "cache"
    a = _copy_core(tmp_path / "install-a")
    first, _ = _probe(a, cache)
    assert first["stats"]["compiled"] > 0 and first["stats"]["loaded"] == 0 and first["stats"]["saved"] > 0
    b = _copy_core(tmp_path / "install-b")  # new folder, new time stamps
    second, err = _probe(b, cache)
    assert second["stats"]["compiled"] == 0 and second["stats"]["loaded"] > 0, second
    assert second["positions"] == first["positions"] and second["cache"] == first["cache"]
    assert "note" not in err
    assert not [p for p in (a / "core").rglob("*") if p.suffix in (".nbi", ".nbc")]


@pytest.fixture(scope="module")
def clean_install(tmp_path_factory):
    """A copy of core/ with its probe kernels compiled into a cache: (package folder, cache, probe report)."""
    root = tmp_path_factory.mktemp("clean")
    pkg = _copy_core(root / "install")
    report, _ = _probe(pkg, root / "cache", code=SMALL_PROBE)
    assert report["stats"]["saved"] == 2
    return pkg, root / "cache", report


@pytest.mark.parametrize("damage", ["truncated", "zeroed", "random", "bit_flip", "foreign"])
def test_a_damaged_cache_entry_costs_a_compile_with_a_note(tmp_path, damage, clean_install):
    """Every kind of damage to an entry is detected before it is unpickled (checksum, key): the kernel is
    compiled again, the result is the same, one line says so, and the rewritten entry loads next time."""
    import random

    pkg, clean_cache, clean = clean_install
    cache = tmp_path / "cache"
    shutil.copytree(clean_cache, cache)
    files = sorted(cache.rglob("*.nbc"))
    assert len(files) == 2  # ("foreign" swaps the two entries)
    rnd = random.Random(damage)
    for f in files:
        blob = bytearray(f.read_bytes())
        if damage == "truncated":
            blob = blob[: len(blob) // 2]
        elif damage == "zeroed":
            blob = bytearray(len(blob))
        elif damage == "random":
            blob = bytearray(rnd.randbytes(len(blob)))
        elif damage == "bit_flip":
            i = rnd.randrange(40, len(blob))
            blob[i] ^= 1 << rnd.randrange(8)
        f.write_bytes(bytes(blob))
    if damage == "foreign":  # another kernel's entry under this one's name (a race of two writers)
        blobs = [f.read_bytes() for f in files]
        for f, blob in zip(files, blobs[1:] + blobs[:1]):
            f.write_bytes(blob)
    again, err = _probe(pkg, cache, code=SMALL_PROBE)
    assert again["positions"] == clean["positions"]
    assert again["stats"]["rejected"] > 0 and again["stats"]["compiled"] > 0
    notes = [line for line in err.splitlines() if line.startswith("ladar: note:")]
    assert len(notes) == 1 and "compiling it again" in notes[0], err[-2000:]
    assert "Traceback" not in err
    healed, err = _probe(pkg, cache, code=SMALL_PROBE)
    assert healed["stats"]["compiled"] == 0 and healed["stats"]["rejected"] == 0 and not err.strip()


def test_an_unwritable_cache_costs_only_the_keeping(tmp_path):
    """A cache path that cannot be created (a file where the folder should be): the run works, one line says the
    kernels are not kept, and nothing is written into the package."""
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    pkg = _copy_core(tmp_path / "install")
    report, err = _probe(pkg, blocker / "cache", code=SMALL_PROBE)
    assert report["stats"]["compiled"] > 0 and report["stats"]["saved"] == 0 and report["stats"]["unsaved"] > 0
    notes = [line for line in err.splitlines() if line.startswith("ladar: note:")]
    assert len(notes) == 1 and "not kept" in notes[0]
    assert not [p for p in (pkg / "core").rglob("*") if p.suffix in (".nbi", ".nbc")]


def test_a_full_disk_while_saving_leaves_no_partial_entry(tmp_path, monkeypatch):
    """The write fails half-way (ENOSPC): no temporary or partial file stays, the caller gets the error (which
    KernelCache.save_overload turns into a note)."""
    import errno

    from core import jit

    files = jit._EntryFiles(str(tmp_path), "probe.f-1.py311")
    real_open = open

    class Full:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            self.f.write(data[: len(data) // 3])
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("builtins.open", lambda p, m="r", *a, **k: Full(real_open(p, m, *a, **k)) if "w" in m
                        else real_open(p, m, *a, **k))
    with pytest.raises(OSError):
        files.save(("sig",), {"payload": 1})
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
    files.save(("sig",), {"payload": 1})
    assert files.load(("sig",)) == {"payload": 1}


def test_two_runs_compiling_at_once_both_work_and_the_next_loads(tmp_path):
    """Two processes compile the same kernels into one empty cache at the same time: each writes whole entries
    (temporary file, then rename), both give the same result, and a third run loads every kernel."""
    import json

    cache = tmp_path / "cache"
    pkg = _copy_core(tmp_path / "install")
    env = {k: v for k, v in os.environ.items() if k not in DROP}
    env.update(LADAR_KERNEL_CACHE=str(cache), PYTHONDONTWRITEBYTECODE="1")
    procs = [subprocess.Popen([sys.executable, "-c", SMALL_PROBE.format(pkg=str(pkg))], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env, cwd=pkg) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-2000:] for o in outs]
    results = [json.loads(o[0].strip().splitlines()[-1]) for o in outs]
    assert results[0]["positions"] == results[1]["positions"]
    assert not list(cache.rglob("*.tmp.*"))
    third, err = _probe(pkg, cache, code=SMALL_PROBE)
    assert third["stats"]["compiled"] == 0 and third["positions"] == results[0]["positions"] and not err.strip()

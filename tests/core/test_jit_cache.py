"""core/jit.py: the compiled kernels' cache goes to a writable per-user folder, never into the package (an
installed Blender extension), whether numba is imported by us first or was imported before (another add-on)."""
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

RUN = """
import sys
{pre}
sys.path.insert(0, {pkg!r})
import numpy as np
from core.config.settings import DetectionSettings
from core.physics.detection.peaks import detect_echoes
import core.jit
w = np.zeros((1, 16)); w[0, 5:8] = (1.0, 3.0, 1.0)
e = detect_echoes(w, DetectionSettings())
assert len(e.pixel) == 1 and abs(e.position_bins[0] - 6.5) < 1e-12
print(core.jit.CACHE_DIR)
"""


@pytest.mark.parametrize("numba_first", [False, True])
def test_kernel_cache_goes_to_the_user_folder_not_the_package(tmp_path, numba_first):
    pkg = tmp_path / "extension"
    shutil.copytree(REPO / "core", pkg / "core", ignore=shutil.ignore_patterns("__pycache__"))
    for p in pkg.rglob("*"):  # a read-only install (root ignores the bits: the file check below decides)
        p.chmod(p.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    home = tmp_path / "home"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "LOCALAPPDATA")}
    env.update(HOME=str(home), USERPROFILE=str(home), PYTHONDONTWRITEBYTECODE="1")
    code = RUN.format(pre="import numba" if numba_first else "", pkg=str(pkg))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    cache = Path(out.stdout.strip().splitlines()[-1])
    if sys.platform.startswith("linux"):
        assert cache.parent == home / ".cache" / "ladar_simulator" / "numba"
    assert home in cache.parents
    assert list(cache.rglob("*.nbi")), "no kernel cached in the per-user folder"
    assert not [p for p in pkg.rglob("*") if p.suffix in (".nbi", ".nbc")], "kernel cache written into the package"
    for p in pkg.rglob("*"):
        p.chmod(p.stat().st_mode | stat.S_IWUSR)


def _cache_dir_of(pkg: Path, home: Path, numba_cache_dir=None) -> Path:
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "LOCALAPPDATA")}
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
    # a child process inherits NUMBA_CACHE_DIR as its parent set it (ending in the digest): the same folder
    assert _cache_dir_of(a, home, numba_cache_dir=first) == first
    assert _cache_dir_of(a, home, numba_cache_dir=tmp_path / "mine") == tmp_path / "mine" / first.name


def test_only_stale_digest_folders_beside_the_cache_are_pruned(tmp_path):
    import time

    from core.jit import prune_stale_caches

    parent = tmp_path / "numba"
    current, stale, fresh = parent / "0123456789abcdef", parent / "fedcba9876543210", parent / "00000000aaaaaaaa"
    other = parent / "core_1491019fea487c031e0fdc1b53f8b1f2"  # not a digest folder: never ours to remove
    for d in (stale, fresh, other):
        (d / "x").mkdir(parents=True)
    old = time.time() - 31 * 86400.0
    for d in (stale, other):
        os.utime(d, (old, old))
    assert prune_stale_caches(current) == [stale]
    assert sorted(p.name for p in parent.iterdir()) == sorted([current.name, fresh.name, other.name])
    assert time.time() - current.stat().st_mtime < 60  # marked as used



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

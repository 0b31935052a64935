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
        assert cache == home / ".cache" / "ladar_simulator" / "numba"
    assert home in cache.parents
    assert list(cache.rglob("*.nbi")), "no kernel cached in the per-user folder"
    assert not [p for p in pkg.rglob("*") if p.suffix in (".nbi", ".nbc")], "kernel cache written into the package"
    for p in pkg.rglob("*"):
        p.chmod(p.stat().st_mode | stat.S_IWUSR)

"""core/jit.py: one compiled kernel serves every import name of the same source (issue 25).  Kernels compiled in
a process that imports the checkout as ``core`` are loaded, none compiled, in a process that imports a copy of
the same source as a Blender extension (``bl_ext.user_default.ladar_simulator.core``), and the reverse.  Two
copies of the core in one process do not share numba's names: the first claims the canonical module name
(``ladar_kernels``), the second keeps its own import name and cache folder, and each copy's kernels, compiled or
loaded, are bound to its own modules and give the same results."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DROP = ("NUMBA_CACHE_DIR", "LADAR_KERNEL_CACHE", "XDG_CACHE_HOME", "LOCALAPPDATA", "PYTHONPATH")
EXT = "bl_ext.user_default.ladar_simulator.core"

#: Two small kernels of core/ (a scalar one, one on arrays: two cache entries, about 1 s of CPU to compile) run
#: through the core imported as each name of NAMES (sys.path: PATHS), in that order, in one process.
PROBE = """
import importlib, json, pickle, sys
sys.path[:0] = {paths!r}
import numpy as np
report = {{}}
for name in {names!r}:
    peaks = importlib.import_module(name + ".physics.detection.peaks")
    jit = importlib.import_module(name + ".jit")
    found = [peaks.interpolate_at(1.0, 3.0, 1.5, 2), peaks.interpolate_at(2.0, 5.0, 1.0, 1)]
    cand = np.array([4, 7, 9, 12])
    kept = peaks._compact(cand, np.array([True, False, True, True]), 4)
    assert kept == 3 and cand[:3].tolist() == [4, 9, 12]
    assert pickle.loads(pickle.dumps(peaks.interpolate_at)) is peaks.interpolate_at
    kernels = {{}}
    for disp in (peaks.interpolate_at, peaks._compact):
        for cres in disp.overloads.values():
            fd = cres.fndesc
            kernels[disp.__name__] = {{
                "modname": fd.modname, "mangled": fd.mangled_name, "env": cres.environment.env_name,
                "own_globals": cres.environment.globals is vars(peaks),
                "own_module": fd.lookup_module() is peaks}}
    report[name] = {{"shared": jit.SHARED, "dir": str(jit.KERNEL_DIR.relative_to(jit.CACHE_DIR)),
                    "stats": dict(jit.CACHE_STATS), "kernels": kernels,
                    "values": [float(x).hex() for p in found for x in p]}}
print(json.dumps(report))
"""


def _run(paths, names, cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in DROP}
    env.update(LADAR_KERNEL_CACHE=str(cache), PYTHONDONTWRITEBYTECODE="1")
    code = PROBE.format(paths=[str(p) for p in paths], names=list(names))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=cache.parent)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "ladar: note" not in out.stderr, out.stderr  # no entry rejected, none left unsaved
    return json.loads(out.stdout.strip().splitlines()[-1])


def _extension(dest: Path) -> Path:
    """A copy of core/ as Blender installs the extension: ``bl_ext/user_default/ladar_simulator/core``."""
    pkg = dest / "bl_ext" / "user_default" / "ladar_simulator"
    shutil.copytree(REPO / "core", pkg / "core", ignore=shutil.ignore_patterns("__pycache__"))
    for d in (dest / "bl_ext", dest / "bl_ext" / "user_default", pkg):
        (d / "__init__.py").write_text("")
    return dest


def _entries(cache: Path) -> dict:
    """Kernel entries per folder below the source digest (``ladar_kernels`` or an import name)."""
    (digest,) = [d for d in cache.iterdir() if d.is_dir()]
    return {d.name: len(list(d.rglob("*.nbc"))) for d in digest.iterdir() if d.is_dir()}


@pytest.mark.parametrize("first,then", [("core", EXT), (EXT, "core")], ids=["checkout-then-extension",
                                                                           "extension-then-checkout"])
def test_kernels_compiled_under_one_import_name_load_under_another(tmp_path, first, then):
    ext = _extension(tmp_path / "ext")
    path = {"core": REPO, EXT: ext}
    cache = tmp_path / "cache"
    a = _run([path[first]], [first], cache)[first]
    assert a["shared"] and a["dir"] == "ladar_kernels"
    assert a["stats"]["compiled"] >= 2 and a["stats"]["loaded"] == 0 and a["stats"]["saved"] == a["stats"]["compiled"]
    for k in a["kernels"].values():
        assert k["modname"] == "ladar_kernels.physics.detection.peaks" and k["own_globals"] and k["own_module"]
    assert _entries(cache) == {"ladar_kernels": a["stats"]["saved"]}
    b = _run([path[then]], [then], cache)[then]
    # every kernel loaded from the entries the other import name compiled, none compiled, nothing new saved
    assert b["stats"]["compiled"] == 0 and b["stats"]["loaded"] == a["stats"]["compiled"], b["stats"]
    assert b["stats"]["saved"] == 0 and b["stats"]["rejected"] == 0
    assert b["values"] == a["values"]
    for name, k in b["kernels"].items():  # the loaded code is the compiled code, bound to this copy's module
        assert k["mangled"] == a["kernels"][name]["mangled"] and k["own_globals"] and k["own_module"]
    assert _entries(cache) == {"ladar_kernels": a["stats"]["saved"]}


@pytest.mark.parametrize("order", [("core", "core_copy"), ("core_copy", "core")], ids=["checkout-first",
                                                                                      "copy-first"])
def test_two_copies_in_one_process_keep_their_own_names_globals_and_entries(tmp_path, order):
    """The second copy of the core imported in a process does not claim the canonical name: its kernels are
    named, filed and bound by its own import name (numba's one JIT never holds two definitions of one symbol,
    and no copy's kernels run on the other copy's module globals), compiled in a cold cache and loaded in a
    warm one; both copies give the same results."""
    other = tmp_path / "other"
    shutil.copytree(REPO / "core", other / "core_copy", ignore=shutil.ignore_patterns("__pycache__"))
    cache = tmp_path / "cache"
    runs = [_run([REPO, other], order, cache) for _ in range(2)]  # cold, then warm
    first, second = order
    for n, run in enumerate(runs):
        a, b = run[first], run[second]
        assert a["shared"] and a["dir"] == "ladar_kernels"
        assert not b["shared"] and b["dir"] == second
        assert a["values"] == b["values"]
        for name in ("interpolate_at", "_compact"):
            ka, kb = a["kernels"][name], b["kernels"][name]
            assert ka["modname"] == "ladar_kernels.physics.detection.peaks"
            assert kb["modname"] == f"{second}.physics.detection.peaks"
            assert "ladar_kernels" not in kb["mangled"] and "ladar_kernels" not in kb["env"]
            assert ka["mangled"] != kb["mangled"] and ka["env"] != kb["env"]
            assert ka["own_globals"] and ka["own_module"] and kb["own_globals"] and kb["own_module"]
        for r in (a, b):
            if n == 0:
                assert r["stats"]["compiled"] >= 2 and r["stats"]["loaded"] == 0, r["stats"]
            else:
                assert r["stats"]["compiled"] == 0 and r["stats"]["loaded"] >= 2, r["stats"]
    saved = runs[0][first]["stats"]["saved"], runs[0][second]["stats"]["saved"]
    assert _entries(cache) == {"ladar_kernels": saved[0], second: saved[1]}

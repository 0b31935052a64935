"""Output files respect the user's umask (issue 14): run folders were 0700 and PNG, LAS files 0600 (made by
tempfile.mkdtemp/mkstemp and renamed into place), so colleagues on a shared server could not open a run."""
import os
import stat

import numpy as np
import pytest

from core.fileio.las import write_run_las
from core.fileio.preview import write_run_previews
from core.fileio.staging import new_temp_dir, new_temp_file
from core.sequence import run_sequence
from core.run import run_simulation
from scenes import config_for, plate


@pytest.fixture(params=[0o022, 0o077, 0o002])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def _modes(root):
    """{relative path: permission bits} of root and everything below it."""
    out = {".": stat.S_IMODE(os.stat(root).st_mode)}
    for dirpath, dirs, files in os.walk(root):
        for name in dirs + files:
            p = os.path.join(dirpath, name)
            out[os.path.relpath(p, root)] = stat.S_IMODE(os.stat(p).st_mode)
    return out


def _check(root, mask, include_root=True):
    for rel, mode in _modes(root).items():
        if rel == "." and not include_root:  # pytest makes tmp_path 0700
            continue
        is_dir = os.path.isdir(os.path.join(root, rel))
        assert mode == (0o777 if is_dir else 0o666) & ~mask, f"{rel}: {oct(mode)} under umask {oct(mask)}"


def test_run_folder_previews_and_las_follow_the_umask(tmp_path, umask):
    cfg = config_for(100.0, pixels=4, subsamples=2, bins=128)
    path, _ = run_simulation(plate(100.0, 2.0), np.eye(4), cfg, tmp_path / "run")
    written = write_run_previews(path)
    assert {p.name for p in written} >= {"range.png", "intensity.png", "energy.png"}
    assert (path / "points.las").is_file()
    write_run_las(path, tmp_path / "export" / "cloud.las")
    _check(path, umask)
    _check(tmp_path / "export", umask)


def test_sequence_folder_follows_the_umask(tmp_path, umask):
    cfg = config_for(100.0, pixels=4, subsamples=2, bins=128)
    scene = plate(100.0, 2.0)
    path, _ = run_sequence([1, 2], lambda f: scene, lambda f: np.eye(4), cfg, tmp_path / "seq")
    _check(path, umask)


def test_temporary_names_are_new_each_time(tmp_path, umask):
    dirs = {new_temp_dir(tmp_path, ".x-") for _ in range(20)}
    files = set()
    for _ in range(20):
        fd, p = new_temp_file(tmp_path, ".f-", ".tmp")
        os.close(fd)
        files.add(p)
    assert len(dirs) == 20 and len(files) == 20
    _check(tmp_path, umask, include_root=False)

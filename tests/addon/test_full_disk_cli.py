"""A full disk in the middle of a run through the command line (issue 31): with 8 KiB free (inside the first EXR,
which gave a traceback from the OpenEXR binding) and 200 KiB free (inside the PLY writer), ``ladar_run.py …
simulate`` exits 1 with one ``ladar: error: No space left on device: <file>; nothing of the run was written``
line, no traceback, and the small disk holds nothing of the run.  A tmpfs in a private mount namespace
(``unshare``), where allowed; every writer is covered in tests/core/fileio/test_full_disk.py."""
import os
import sys
from pathlib import Path

import pytest

from tests.small_disk import on_tmpfs

REPO = Path(__file__).resolve().parents[2]
BLEND = REPO / "sample_blends" / "flash_demo.blend"

FILL = """
import os, sys
disk, free = sys.argv[1], int(sys.argv[2])
st = os.statvfs(disk)
fd = os.open(os.path.join(disk, "fill"), os.O_WRONLY | os.O_CREAT)
os.posix_fallocate(fd, 0, st.f_bavail * st.f_frsize - free)
os.close(fd)
"""


@pytest.mark.skipif(sys.platform != "linux", reason="Linux mount namespaces")
@pytest.mark.parametrize("free_kib, where", [(8, "range.exr"), (200, "points.ply")])
def test_a_full_disk_during_a_run_is_one_error_line_and_leaves_nothing(tmp_path, free_kib, where):
    disk = tmp_path / "disk"
    disk.mkdir()
    fill = tmp_path / "fill.py"
    fill.write_text(FILL)
    then = (f"{sys.executable} {fill} {disk} {free_kib * 1024} && {sys.executable} {REPO / 'scripts' / 'ladar_run.py'} "
            f"{BLEND} simulate --no-import --out {disk / 'r'}; echo EXIT $?; ls -A {disk}")
    done = on_tmpfs(disk, then, size="8m", cwd=tmp_path, env=dict(os.environ, TMPDIR=str(tmp_path)))
    err = done.stderr.strip().splitlines()
    assert "Traceback" not in done.stderr and "EXIT 1" in done.stdout, done.stdout[-1000:] + done.stderr[-3000:]
    assert err[-1].startswith("ladar: error: No space left on device: "), err
    assert where in err[-1] and err[-1].endswith("; nothing of the run was written"), err[-1]
    assert done.stdout.strip().splitlines()[-1] == "fill", done.stdout[-500:]  # nothing of the run on the disk

"""Every writer's failure is an OSError naming its file, and leaves nothing (issue 31): on a small tmpfs (a
private mount namespace, ``unshare``, where allowed), filled so that the disk becomes full inside each file of a
run in turn — EXR, PLY, NPZ, LAS, NPY, JSON, PNG — the run raises OSError(ENOSPC) naming that file, and nothing
of it is left (the command line prints such an error as its one ``ladar: error: …`` line).  Before, a full disk
inside the EXR writer was a RuntimeError from the OpenEXR binding: a traceback."""
import errno
import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from core.fileio.run_folder import write_exr
from tests.small_disk import on_tmpfs

REPO = Path(__file__).resolve().parents[3]
#: The files of a flash run in the order they are written (core.fileio.run_folder.write_run_files, then the
#: previews: core.fileio.preview.write_run_previews).
ORDER = ["range.exr", "intensity.exr", "energy.exr", "points.ply", "points.npz", "points.las", "echoes.npz",
         "waveforms.npy", "metadata.json", "range.png", "intensity.png", "energy.png"]

_ON_A_SMALL_DISK = textwrap.dedent("""
    import errno, json, os, shutil, sys
    sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[1] + "/tests/core")
    from pathlib import Path
    import numpy as np
    from core.fileio.preview import write_run_previews
    from core.fileio.staging import claim_run_dir
    from core.run import run_simulation
    from scenes import config_for, plate
    disk = Path(sys.argv[2])

    def run(out):  # as the add-on's job: the products, the PNG previews, then the rename into place
        with claim_run_dir(out) as claim:
            run_simulation(plate(100.0, 10.0), np.eye(4), config_for(100.0, pixels=16), claim.work)
            write_run_previews(claim.work)
            return claim.commit()

    def free():
        st = os.statvfs(disk)
        return st.f_bavail * st.f_frsize

    probe = run(disk / "probe")
    pages = {str(p.relative_to(probe)): -(-p.stat().st_size // 4096) for p in probe.rglob("*") if p.is_file()}
    shutil.rmtree(probe)
    order = json.loads(sys.argv[3])  # the order the run writes its files in
    outcomes = []

    def attempt(n):  # a run with n pages free: the file it failed in (None: written)
        fill = disk / "fill"
        fill.unlink(missing_ok=True)
        fd = os.open(fill, os.O_WRONLY | os.O_CREAT)
        os.posix_fallocate(fd, 0, free() - n * 4096)
        os.close(fd)
        try:
            out = run(disk / "r")
            outcomes.append((n, "written"))
            shutil.rmtree(out)
            name = None
        except OSError as exc:
            name = os.path.basename(exc.filename or "")
            outcomes.append((n, exc.__class__.__name__, exc.errno, name))
        except BaseException as exc:
            outcomes.append((n, exc.__class__.__name__, str(exc)[:300]))
            name = "?"
        left = sorted(p.name for p in disk.iterdir() if p.name != "fill")
        if left:
            outcomes.append((n, "LEFT", left))
        return name

    hits = {}
    offset = 0  # pages the run's claims take before the first product
    while attempt(offset) == "ladar-owner.json" and offset < 8:
        offset += 1
    for k, name in enumerate(order):  # free space for the disk to fill up inside each file in turn
        lo = offset + sum(pages.get(f, 0) for f in order[:k])
        for n in range(max(lo - 4, 0), lo + pages.get(name, 1) + 4):
            got = attempt(n)
            if got == name:
                hits[name] = n
                break
            if got is None:  # the whole run fits: more free space cannot fail inside this file
                break
    files = sorted(pages)
    print("RESULT " + json.dumps({"files": files, "hits": hits, "outcomes": outcomes}), flush=True)
""")


@pytest.mark.skipif(sys.platform != "linux", reason="Linux mount namespaces")
def test_a_full_disk_inside_every_writer_is_one_oserror_naming_the_file_and_leaves_nothing(tmp_path):
    disk = tmp_path / "disk"
    disk.mkdir()
    script = tmp_path / "on_a_small_disk.py"
    script.write_text(_ON_A_SMALL_DISK)
    done = on_tmpfs(disk, f"exec {sys.executable} {script} {REPO} {disk} '{json.dumps(ORDER)}'", size="4m")
    line = next((x for x in done.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert line, done.stdout[-2000:] + done.stderr[-3000:]
    res = json.loads(line[len("RESULT "):])
    failures = [o for o in res["outcomes"] if o[1] != "written"]
    # every failure: OSError(ENOSPC) naming a file of the run, and nothing left on the disk
    assert all(o[1] == "OSError" and o[2] == errno.ENOSPC and o[3] for o in failures), failures
    assert not [o for o in res["outcomes"] if o[1] == "LEFT"], res["outcomes"]
    assert sorted(res["files"]) == sorted(ORDER), res["files"]  # (a new file: add it to ORDER)
    # the disk became full inside each file of the run, at one amount of free space or another — except that the
    # last file written (the energy preview) can fit in the page slack the earlier files leave (tmpfs rounds each
    # file up to whole pages): with one page less the run fails in an earlier file, with one more it is written
    missed = sorted(set(ORDER) - set(res["hits"]))
    assert missed in ([], [ORDER[-1]]), (res["hits"], res["outcomes"])


def test_the_exr_writer_fails_with_an_oserror_naming_the_file(tmp_path):
    """A vanished folder (and every other failure of the OpenEXR binding, a RuntimeError) is an OSError."""
    path = tmp_path / "gone" / "range.exr"
    with pytest.raises(OSError) as info:
        write_exr(path, {"Y": np.zeros((4, 4), np.float32)})
    assert info.value.errno == errno.ENOENT and info.value.filename == str(path), info.value

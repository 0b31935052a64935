"""Run folders never destroy a user's files (core/fileio/staging.py, core/fileio/locks.py, core/process.py):

* ``overwrite`` replaces only a previous run of this tool (its metadata.json), never another folder, the current
  folder, a folder containing it or a mount point;
* a run claims its folder's name before it starts: a second run of the same name refuses, or (``new``) takes
  the next name;
* a staging folder left by a dead run (SIGKILL) is removed by the next run — and only such folders;
* run names up to the file system's 255-byte limit work (the staging name is short whatever the run name);
* signals end a command like Ctrl-C, never in the middle of a rename; output survives a closed pipe.
"""
import io
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import core.process as process
from core.errors import ConfigError
from core.fileio.locks import OWNER_FILE
from core.fileio.staging import claim_run_dir, is_run_folder, staging_path
from core.sequence import run_sequence
from core.run import run_simulation
from scenes import config_for, plate
from tests.small_disk import on_tmpfs

REPO = Path(__file__).resolve().parents[3]


def _run(out, **kw):
    return run_simulation(plate(100.0, 10.0), np.eye(4), config_for(100.0, pixels=4), out, **kw)


def _names(folder):
    return sorted(p.name for p in Path(folder).iterdir())


# ------------------------------------------------------------------------------------------------------------
# overwrite replaces only a run
# ------------------------------------------------------------------------------------------------------------
def test_overwrite_refuses_a_folder_that_is_not_a_run(tmp_path):
    folder = tmp_path / "d"
    folder.mkdir()
    (folder / "thesis.txt").write_text("data")
    with pytest.raises(ConfigError) as info:
        _run(folder, overwrite=True)
    assert info.value.field == "out" and str(folder) in str(info.value)
    assert "previous run" in str(info.value)
    assert (folder / "thesis.txt").read_text() == "data"
    assert _names(tmp_path) == ["d"] and _names(folder) == ["thesis.txt"]  # nothing hidden left either


@pytest.mark.parametrize("metadata", ['{"format": "something-else"}', "not json", '["ladar-run"]', ""])
def test_a_metadata_file_that_is_not_ours_does_not_make_a_run(tmp_path, metadata):
    folder = tmp_path / "d"
    folder.mkdir()
    (folder / "metadata.json").write_text(metadata)
    assert not is_run_folder(folder)
    with pytest.raises(ConfigError, match="previous run"):
        _run(folder, overwrite=True)
    assert (folder / "metadata.json").read_text() == metadata


def test_overwrite_replaces_a_previous_run_and_a_sequence(tmp_path):
    path, _ = _run(tmp_path / "r")
    (path / "extra.txt").write_text("a product of the old run")
    assert is_run_folder(path)
    _run(tmp_path / "r", overwrite=True)
    assert "extra.txt" not in _names(path) and is_run_folder(path)
    cfg = config_for(100.0, pixels=4)
    seq, _ = run_sequence([1, 2], lambda f: plate(100.0, 10.0), lambda f: np.eye(4), cfg, tmp_path / "s")
    assert json.loads((seq / "metadata.json").read_text())["format"] == "ladar-sequence" and is_run_folder(seq)
    run_sequence([1], lambda f: plate(100.0, 10.0), lambda f: np.eye(4), cfg, tmp_path / "s", overwrite=True)
    assert json.loads((seq / "metadata.json").read_text())["frames"] == [1]
    assert _names(tmp_path) == ["r", "s"]


def test_overwrite_never_replaces_the_current_folder_or_one_containing_it(tmp_path, monkeypatch):
    path, _ = _run(tmp_path / "r")
    inner = path / "notes"
    inner.mkdir()
    for cwd, out in ((path, "."), (inner, "..")):
        monkeypatch.chdir(cwd)
        with pytest.raises(ConfigError, match="current folder"):
            _run(out, overwrite=True)
    assert is_run_folder(path) and (path / "notes").is_dir()
    # and a current folder with the user's files is not a run: refused too
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("data")
    with pytest.raises(ConfigError):
        _run(".", overwrite=True)
    assert (tmp_path / "notes.txt").read_text() == "data"


def test_overwrite_refuses_a_mount_point_and_leaves_nothing(tmp_path, monkeypatch):
    path, _ = _run(tmp_path / "m")
    real_ismount = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: os.path.realpath(p) == str(path) or real_ismount(p))
    with pytest.raises(ConfigError, match="mount point"):
        _run(path, overwrite=True)
    assert _names(tmp_path) == ["m"]  # no empty ".old-…" folder, no staging


def test_a_run_replaced_by_someone_else_meanwhile_is_not_overwritten(tmp_path):
    """The folder is checked again when the new run is moved into place."""
    _run(tmp_path / "r")
    claim = claim_run_dir(tmp_path / "r", if_exists="replace")
    with claim:
        claim.work.mkdir()
        (claim.work / "metadata.json").write_text('{"format": "ladar-run"}')
        for f in (tmp_path / "r").iterdir():  # the user replaced the run by their own files during the run
            f.unlink()
        (tmp_path / "r" / "thesis.txt").write_text("data")
        with pytest.raises(ConfigError, match="previous run"):
            claim.commit()
    assert _names(tmp_path / "r") == ["thesis.txt"] and _names(tmp_path) == ["r"]


# ------------------------------------------------------------------------------------------------------------
# names are claimed before the run
# ------------------------------------------------------------------------------------------------------------
def test_a_claimed_name_is_refused_or_skipped(tmp_path):
    _run(tmp_path / "r")
    with claim_run_dir(tmp_path / "r", if_exists="replace") as held:
        with pytest.raises(ConfigError, match="another run is writing") as info:
            _run(tmp_path / "r", overwrite=True)
        assert f"pid {os.getpid()}" in str(info.value)
        with claim_run_dir(tmp_path / "r", if_exists="new") as second:
            assert second.path == tmp_path / "r_2"
            with claim_run_dir(tmp_path / "r", if_exists="new") as third:
                assert third.path == tmp_path / "r_3"
        assert held.path == tmp_path / "r"
    assert _names(tmp_path) == ["r"]
    with claim_run_dir(tmp_path / "r", if_exists="new") as again:  # the free name after the releases
        assert again.path == tmp_path / "r_2"


_HOLDER = textwrap.dedent("""
    import os, sys
    sys.path.insert(0, sys.argv[1])
    from core.fileio.staging import claim_run_dir
    claim = claim_run_dir(sys.argv[2], if_exists=sys.argv[3])
    if sys.argv[4] == "mid-commit":  # die between the two renames of a replacement
        os.rename(claim.path, claim.staging / "old")
        os._exit(0)
    print("claimed", flush=True)
    sys.stdin.readline()
""")


def _holder(out, mode="stop", stage="hold"):
    p = subprocess.Popen([sys.executable, "-c", _HOLDER, str(REPO), str(out), mode, stage], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True)
    if stage == "hold":
        assert p.stdout.readline().strip() == "claimed"
    else:
        p.wait(60)
    return p


def test_another_process_holding_the_name_is_refused_and_its_leftovers_removed_once_it_is_killed(tmp_path):
    _run(tmp_path / "r")
    before = (tmp_path / "r" / "metadata.json").read_bytes()
    holder = _holder(tmp_path / "r", "replace")
    try:
        with pytest.raises(ConfigError, match=f"another run is writing this one \\(pid {holder.pid} "):
            _run(tmp_path / "r", overwrite=True)
        assert staging_path(tmp_path / "r").is_dir()
        with claim_run_dir(tmp_path / "other") as claim:  # a live run's staging is left alone
            assert claim.path.name == "other"
        assert staging_path(tmp_path / "r").is_dir()
    finally:
        holder.kill()
        holder.wait()
    assert staging_path(tmp_path / "r").is_dir()  # SIGKILL: nothing could clean up
    path, _ = _run(tmp_path / "x")  # the next run, even for another name, removes it
    assert _names(tmp_path) == ["r", "x"]
    assert (tmp_path / "r" / "metadata.json").read_bytes() == before


def test_a_run_killed_between_its_two_renames_gets_the_previous_run_back(tmp_path):
    _run(tmp_path / "r")
    before = (tmp_path / "r" / "metadata.json").read_bytes()
    _holder(tmp_path / "r", "replace", "mid-commit")
    assert not (tmp_path / "r").exists() and (staging_path(tmp_path / "r") / "old" / "metadata.json").is_file()
    _run(tmp_path / "y")
    assert _names(tmp_path) == ["r", "y"]
    assert (tmp_path / "r" / "metadata.json").read_bytes() == before


def test_only_abandoned_staging_folders_of_this_tool_are_removed(tmp_path, monkeypatch):
    foreign = tmp_path / ".mine.ladar-staging"  # not ours: no owner file of this tool
    foreign.mkdir()
    (foreign / OWNER_FILE).write_text('{"tool": "someone-else"}')
    young = tmp_path / ".young.0123456789abcdef.ladar-staging"  # a claim being created this instant
    young.mkdir()
    legacy = tmp_path / ".r.partial-abc123"  # left by an older version: cannot tell, kept
    legacy.mkdir()
    _run(tmp_path / "r")
    assert _names(tmp_path) == sorted([foreign.name, young.name, legacy.name, "r"])
    monkeypatch.setattr("core.fileio.locks.OWNERLESS_GRACE_S", 0.0)  # an owner-less claim this old: its creator died
    time.sleep(0.01)
    _run(tmp_path / "s")
    assert _names(tmp_path) == sorted([foreign.name, legacy.name, "r", "s"])


def test_a_run_killed_while_removing_its_staging_leaves_nothing_the_next_claim_keeps(tmp_path):
    """A claim is removed by renaming it to its removal name while still locked, then unlocking and deleting it.
    A process killed after its owner file was deleted (seen in a sweep whose worker was killed) leaves an
    empty folder under the removal name: removed by the next claim at once, not after the owner-less grace."""
    claim = claim_run_dir(tmp_path / "r")
    renamed = []
    real_rename = os.rename

    def spy(src, dst):
        renamed.append((Path(src).name, Path(dst).name))
        return real_rename(src, dst)

    import core.fileio.staging as staging
    staging.os.rename = spy
    try:
        claim.release()
    finally:
        staging.os.rename = real_rename
    assert renamed and renamed[0][0] == staging_path(tmp_path / "r").name and ".removing-" in renamed[0][1]
    assert _names(tmp_path) == []
    cut_short = tmp_path / renamed[0][1]  # what a kill between deleting the owner file and the folder leaves
    cut_short.mkdir()
    young = tmp_path / ".young.0123456789abcdef.ladar-staging"  # an owner-less claim being made: kept
    young.mkdir()
    _run(tmp_path / "s")
    assert _names(tmp_path) == sorted([young.name, "s"])


# ------------------------------------------------------------------------------------------------------------
# names up to the file system's limit
# ------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["r" * 240, "r" * 250, "r" * 255, "é" * 127 + "r"])
def test_a_legal_long_run_name_works(tmp_path, name):
    assert len(os.fsencode(name)) <= 255
    path, _ = _run(tmp_path / name)
    assert path.name == name and is_run_folder(path)
    assert len(os.fsencode(staging_path(path).name)) < 150
    _run(tmp_path / name, overwrite=True)
    assert _names(tmp_path) == [name]


def test_a_name_over_the_limit_is_a_clean_error(tmp_path):
    with pytest.raises(ConfigError, match="at most 255 bytes"):
        _run(tmp_path / ("r" * 256))
    with claim_run_dir(tmp_path / ("r" * 254), if_exists="new") as claim:
        assert claim.path.name == "r" * 254
        with pytest.raises(ConfigError, match="at most 255 bytes"):  # <name>_2 would not fit
            claim_run_dir(tmp_path / ("r" * 254), if_exists="new")
    assert _names(tmp_path) == []


# ------------------------------------------------------------------------------------------------------------
# signals and output
# ------------------------------------------------------------------------------------------------------------
def test_a_signal_inside_a_deferred_block_waits_for_its_end():
    with process.interrupts_as_exceptions():
        done = []
        with pytest.raises(process.Interrupted) as info:
            with process.deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
                done.append(True)  # not cut in two
        assert done == [True] and info.value.exit_code == 143 and info.value.signal_name == "SIGTERM"
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # handlers restored


def test_sighup_raises_like_ctrl_c_and_cleanup_is_not_interrupted_again():
    with process.interrupts_as_exceptions():
        with pytest.raises(KeyboardInterrupt) as info:
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(1)
        assert process.exit_code(info.value) == 129
        os.kill(os.getpid(), signal.SIGHUP)  # during the clean-up: ignored
        time.sleep(0.05)


def test_a_signal_while_a_claim_is_taken_leaves_no_staging_folder(tmp_path, monkeypatch):
    """A signal arriving while the claim is created (mkdir, owner file: a deferred block) is raised as the block
    ends, before the claim reaches its holder: the claim is released there, nothing is left (the CI failure of
    session 27: a staging folder after SIGTERM)."""
    import core.fileio.staging as staging

    real = staging.lock_new_folder

    def lock_then_signal(*args, **kw):
        lock = real(*args, **kw)
        os.kill(os.getpid(), signal.SIGTERM)  # pending until the deferred block ends
        time.sleep(0.05)
        return lock

    monkeypatch.setattr(staging, "lock_new_folder", lock_then_signal)
    for mode in ("stop", "new"):
        with process.interrupts_as_exceptions():
            with pytest.raises(process.Interrupted):
                claim_run_dir(tmp_path / "deep" / "r", if_exists=mode)
        assert _names(tmp_path) == [] and staging.release_live_claims() == 0, mode


def test_claims_still_held_are_released_at_the_end_of_a_command(tmp_path):
    """A claim whose holder never got to its clean-up (a signal between ``claim_run_dir`` returning and the
    holder's ``with``/``try``) is released by the command line's last step."""
    from core.fileio.staging import release_live_claims

    claim = claim_run_dir(tmp_path / "r")
    assert claim.staging.is_dir()
    assert release_live_claims() == 1 and _names(tmp_path) == []
    assert release_live_claims() == 0
    claim.release()  # (its holder's own clean-up, later, does nothing)
    assert _names(tmp_path) == []


def test_emit_survives_a_reader_that_went_away():
    read, write = os.pipe()
    os.close(read)
    stream = io.TextIOWrapper(os.fdopen(write, "wb"), encoding="utf-8")
    old = signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    try:
        assert process.emit("progress", stream=stream) is False
        assert process.emit("more progress", stream=stream) is False
        stream.close()  # the interpreter's final flush does not fail either
    finally:
        signal.signal(signal.SIGPIPE, old)



_ON_A_MOUNT = textwrap.dedent("""
    import shutil, sys
    sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[1] + "/tests/core")
    from pathlib import Path
    import numpy as np
    from core.errors import ConfigError
    from core.run import run_simulation
    from scenes import config_for, plate
    parent, mount = Path(sys.argv[2]), Path(sys.argv[3])
    print("MOUNTED", flush=True)
    run, _ = run_simulation(plate(100.0, 10.0), np.eye(4), config_for(100.0, pixels=4), parent / "r")
    for f in run.iterdir():  # the mount holds a previous run
        shutil.copy2(f, mount / f.name)
    try:
        run_simulation(plate(100.0, 10.0), np.eye(4), config_for(100.0, pixels=4), mount, overwrite=True)
        print("REPLACED")
    except ConfigError as exc:
        print("REFUSED", exc)
    except Exception as exc:
        print("FAILED", type(exc).__name__, exc)
""")


@pytest.mark.skipif(sys.platform != "linux", reason="Linux mount namespaces")
def test_overwrite_onto_a_real_mount_point_is_refused_and_leaves_nothing(tmp_path):
    """In a private mount namespace (``unshare``), where allowed: a tmpfs mounted on the run folder."""
    mount = tmp_path / "m"
    mount.mkdir()
    done = on_tmpfs(mount, f"exec {sys.executable} -c '{_ON_A_MOUNT}' {REPO} {tmp_path} {mount}", timeout=120)
    assert "REFUSED" in done.stdout and "mount point" in done.stdout, done.stdout + done.stderr
    assert _names(tmp_path) == ["m", "r"]  # no ".old-…" folder, no staging


def test_single_file_write_is_complete_or_absent(tmp_path):
    """staging.write_file_atomically (previews, LAS, exported configs): all or nothing, no temporary left."""
    from core.fileio.staging import write_file_atomically

    path = tmp_path / "a.txt"
    write_file_atomically(path, lambda f: f.write(b"one"), overwrite=False)
    assert path.read_bytes() == b"one"
    with pytest.raises(FileExistsError):
        write_file_atomically(path, lambda f: f.write(b"two"), overwrite=False)

    def appears_meanwhile(f):  # another writer creates the name while this one writes
        f.write(b"three")
        path.write_bytes(b"theirs")

    path.unlink()
    with pytest.raises(FileExistsError, match="created meanwhile"):
        write_file_atomically(path, appears_meanwhile, overwrite=False)
    assert path.read_bytes() == b"theirs"

    def fails(f):
        f.write(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_file_atomically(path, fails)
    assert path.read_bytes() == b"theirs"
    write_file_atomically(path, lambda f: f.write(b"four"))
    assert path.read_bytes() == b"four"
    assert _names(tmp_path) == ["a.txt"]


@pytest.mark.skipif(os.name != "posix", reason="pid liveness probe is POSIX only")
def test_a_claim_whose_creator_died_writing_its_owner_file_is_taken_at_once(tmp_path):
    """A sweep worker killed right after it made a claim's folder, while writing the owner file under its
    temporary name (host and pid in that name), left an owner-less claim that made the task's retry wait the
    full owner-less grace.  The retry now sees that writer is gone and takes the name at once; a claim whose
    writer is alive (or of another host) is still left alone."""
    import subprocess
    import sys

    from core.fileio.locks import partial_owner_name

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    dead_pid = int(dead.stdout)
    staging = staging_path(tmp_path / "r")
    staging.mkdir()
    (staging / partial_owner_name(dead_pid)).write_bytes(b"")
    alive = staging_path(tmp_path / "s")
    alive.mkdir()
    (alive / partial_owner_name(os.getpid())).write_bytes(b"")
    other_host = staging_path(tmp_path / "t")
    other_host.mkdir()
    (other_host / f".{OWNER_FILE}.000000000000.{dead_pid}.partial").write_bytes(b"")
    t0 = time.monotonic()
    path, _ = _run(tmp_path / "r")  # would have refused ('another run is writing') for OWNERLESS_GRACE_S
    assert time.monotonic() - t0 < 30 and is_run_folder(path)
    assert _names(tmp_path) == sorted(["r", alive.name, other_host.name])
    with pytest.raises(ConfigError, match="no other run is writing"):
        _run(tmp_path / "s")


def test_a_run_folder_that_is_a_symbolic_link_is_refused(tmp_path):
    """Issue 31: a dangling link as the run folder made its target; a link (dangling or to a run) is refused."""
    link = tmp_path / "r"
    link.symlink_to(tmp_path / "target")
    for if_exists in ("stop", "replace"):
        with pytest.raises(ConfigError, match="symbolic link .*target, which does not exist"):
            claim_run_dir(link, if_exists=if_exists)
    assert _names(tmp_path) == ["r"]
    run, _ = _run(tmp_path / "a")
    link.unlink()
    link.symlink_to(run)
    with pytest.raises(ConfigError, match="not a symbolic link"):
        _run(link, overwrite=True)
    assert _names(tmp_path) == ["a", "r"] and (run / "metadata.json").is_file()


@pytest.mark.parametrize("joules, text", [(6.677e-13, "667.7 fJ"), (1.094e-12, "1.094 pJ"), (4.919e-08, "49.19 nJ"),
                                          (2e-7, "200 nJ"), (5e-5, "50 \u00b5J"), (0.1, "100 mJ"), (2.5, "2.5 J"),
                                          (0.0, "0 J"), (9.99996e-13, "1 pJ"), (1e-30, "1e-06 yJ")])
def test_summary_energies_read_on_an_si_prefix(joules, text):
    """The summary's energy line (issue 27): before, "6.677e-13 J at the aperture"."""
    from core.fileio.run_folder import format_energy_j
    assert format_energy_j(joules) == text

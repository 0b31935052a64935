"""The previews' worker processes of a headless ``simulate`` (core/fileio/preview_worker.py) through
``scripts/ladar_run.py``: they start before Blender, draw the PNGs an in-process draw gives byte for byte, and
none (nor its forked drawer) outlives its command, whether the run ends or is terminated (SIGTERM mid-preview: exit 143, no run folder);
``--no-previews`` starts none."""
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
RUN = [sys.executable, str(REPO / "scripts" / "ladar_run.py")]


def _workers(pid: int) -> list[int]:
    """The preview workers among the descendants of process ``pid`` (a worker and its forked drawers)."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            children = (task / "children").read_text().split()
        except OSError:
            continue
        for child in children:
            try:
                cmd = Path(f"/proc/{child}/cmdline").read_bytes()
            except OSError:
                continue
            if b"core.fileio.preview_serve" in cmd:  # (the worker's -c bootstrap)
                found += [int(child)] + _workers(int(child))
    return found


def _gone(pids, wait_s: float = 10.0) -> bool:
    """Every process of ``pids`` has ended (or is a zombie about to be reaped by init)."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        alive = []
        for pid in pids:
            try:
                state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            except OSError:
                continue
            if state != "Z":
                alive.append(pid)
        if not alive:
            return True
        time.sleep(0.05)
    return False


def _run_watching(cmd, cwd, until=None, timeout=900):
    """Run ``cmd``, noting the preview workers it has at each output line; ``until(line)`` true: SIGTERM it.
    Returns (exit code, output, worker pids seen)."""
    env = dict(os.environ, LADAR_PREVIEW_WORKERS="2")  # (by default no worker starts on a busy machine)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1, cwd=cwd,
                            env=env)
    seen, lines = set(), []
    deadline = time.monotonic() + timeout
    try:
        for line in proc.stdout:
            lines.append(line)
            seen.update(_workers(proc.pid))
            if until is not None and until(line):
                proc.send_signal(signal.SIGTERM)
                until = None
            if time.monotonic() > deadline:
                break
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return code, "".join(lines), sorted(seen)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_draw_the_in_process_pngs_and_end_with_the_command(tmp_path):
    """The flash demo twice: with previews (two workers from Blender's start on, gone after the exit) and with
    ``--no-previews`` (no worker); the in-process draw of the second folder gives the first one's PNG bytes."""
    blend = str(REPO / "sample_blends" / "flash_demo.blend")
    code, out, pids = _run_watching([*RUN, blend, "simulate", "--out", str(tmp_path / "w")], tmp_path)
    assert code == 0, out
    assert len(pids) in (1, 2), out  # the worker (and its forked drawer if seen drawing), while the command printed
    assert _gone(pids)
    assert "note:" not in out
    code, out, none = _run_watching([*RUN, blend, "simulate", "--out", str(tmp_path / "n"), "--no-previews"],
                                    tmp_path)
    assert code == 0, out
    assert none == [] and "PNG previews" not in out
    assert not list((tmp_path / "n").rglob("*.png"))
    from core.fileio.preview import write_run_previews

    shutil.copytree(tmp_path / "n", tmp_path / "here")
    write_run_previews(tmp_path / "here")
    pngs = sorted(p.name for p in (tmp_path / "w").glob("*.png"))
    assert pngs == ["energy.png", "intensity.png", "range.png"]
    for name in pngs:
        assert (tmp_path / "w" / name).read_bytes() == (tmp_path / "here" / name).read_bytes(), name


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_while_the_workers_draw_leaves_no_process_and_no_folder(tmp_path):
    """SIGTERM when the gated example's 33 previews have begun: exit 143, "nothing of the run was written", no
    run folder, no staging folder, and both workers are gone."""
    out_dir = tmp_path / "out" / "gated"
    code, out, pids = _run_watching([*RUN, str(REPO / "sample_blends" / "gated_board.blend"), "simulate",
                                     "--out", str(out_dir)], tmp_path,
                                    until=lambda line: re.search(r"PNG previews ([1-9]|[12]\d|3[0-2])/33 ", line))
    assert code == 143, out
    assert "interrupted (SIGTERM): nothing of the run was written" in out
    assert len(pids) in (1, 2), out
    assert _gone(pids)
    assert not out_dir.exists()
    assert not os.path.exists(out_dir.parent) or os.listdir(out_dir.parent) == []


def test_no_previews_starts_no_worker(lad, scene, tmp_path, capsys, monkeypatch):
    """In process (``blender -c ladar``'s handler): ``--no-previews`` never starts the pool."""
    from blender_scenes import add_camera, add_plate

    cam = add_camera(scene, width_px=4, height_px=4, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=2.0, location=(0, 0, -100))
    import importlib

    pool_class = importlib.import_module(lad.package.__name__ + ".core.fileio.preview_worker").PreviewPool
    started = []
    monkeypatch.setattr(pool_class, "start", classmethod(lambda cls, n=None: started.append(n)))
    code = lad.cli.cli_handler(["simulate", "--out", str(tmp_path / "r"), "--no-previews"])
    assert code == 0, capsys.readouterr().err
    assert started == [] and not list((tmp_path / "r").rglob("*.png"))


@pytest.mark.parametrize("killed", [False, True], ids=["worker", "worker-killed"])
def test_workers_of_the_installed_extension_draw_a_runs_previews(lad, scene, tmp_path, capsys, killed):
    """The command handler with a pool the installed add-on's own ``core`` started (as ``blender -c ladar`` does:
    the workers import ``core`` from the extension's folder, with the command's ``sys.path``): the run's PNGs
    are those of an in-process draw, and the workers have ended when the command returns.  ``killed``: the
    worker is killed before the run; the command says so in one note and draws the previews itself."""
    import importlib

    from blender_scenes import add_camera, add_plate

    cam = add_camera(scene, width_px=6, height_px=4, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=2.0, location=(0, 0, -100))
    worker = importlib.import_module(lad.package.__name__ + ".core.fileio.preview_worker")
    pool = worker.PreviewPool.start(2)
    assert len(pool.live()) == 1, pool.notes
    if killed:
        os.kill(pool.workers[0].pid, signal.SIGKILL)
        pool.workers[0].proc.wait()
    code = lad.cli.cli_handler(["simulate", "--out", str(tmp_path / "r")], preview_pool=pool)
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "PNG previews 4/4" in out  # 3 images + the waveform cube (no plot)
    notes = [line for line in (out + err).splitlines() if "note:" in line]
    assert notes == (["ladar: note: no preview worker is running (it exited (code -9) before drawing); the previews "
                      "are drawn here"] if killed else [])
    assert all(w.proc.poll() is not None for w in pool.workers)
    from core.fileio.preview import write_run_previews

    shutil.copytree(tmp_path / "r", tmp_path / "here")
    for png in (tmp_path / "here").glob("*.png"):
        png.unlink()
    write_run_previews(tmp_path / "here")
    names = sorted(p.name for p in (tmp_path / "r").glob("*.png"))
    assert names == ["energy.png", "intensity.png", "range.png"]
    for name in names:
        assert (tmp_path / "r" / name).read_bytes() == (tmp_path / "here" / name).read_bytes(), name

"""core/fileio/preview_worker.py: previews drawn by a worker and its forked drawers are byte for byte those drawn in
process; a drawer killed mid-draw leaves its share to its worker, a worker killed mid-draw its share to the caller
(nothing half-written left); cancel kills the worker and its drawers.
One small gated run (3 images + 9 slices) serves every test; each test draws into its own copy of it."""
import os
import shutil
import signal
import time

import numpy as np
import pytest

from core.config import SimulationConfig
from core.errors import Cancelled
from core.fileio import preview
from core.fileio.preview_worker import PreviewPool, worker_count
from core.run import run_simulation
from scenes import C, plate


@pytest.fixture(scope="module")
def gated_run(tmp_path_factory):
    """(a gated run folder without previews, {relative PNG path: bytes} of one in-process draw of it)."""
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px, cfg.receiver.height_px = 16, 8
    cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad = 8e-3, 4e-3
    cfg.laser.pulse_fwhm_s = 3e-9
    g = cfg.gated
    g.n_slices, g.delay_step_s, g.gate_width_s, g.shutter_edge_s = 9, 2e-9, 10e-9, 2e-9
    g.first_delay_s = 2 * 300.0 / C - 14e-9
    cfg.run.threads = 1
    base = tmp_path_factory.mktemp("preview_worker")
    path, _ = run_simulation(plate(300.0, 20.0), np.eye(4), cfg, base / "gated")
    ref = base / "reference"
    shutil.copytree(path, ref)
    preview.write_run_previews(ref)
    return path, _pngs(ref)


def _pngs(folder) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*.png"))}


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def _hidden(folder):
    return [p for p in folder.rglob(".*")]


def test_shares_partition_the_previews_and_draw_the_same_bytes(gated_run, tmp_path):
    """``share=(k, n)``: the n calls draw each preview exactly once, each the PNG one call draws (the slices
    replayed from another first slice than in one call: FigureReplay's bytes equal a full draw's)."""
    src, ref = gated_run
    assert len(ref) == 12 and preview.preview_count(src) == 12
    folder = _copy(src, tmp_path / "shares")
    names = []
    for k in range(3):
        steps = []
        written = preview.write_run_previews(folder, share=(k, 3), progress=lambda d, t: steps.append((d, t)))
        names += [p.relative_to(folder).as_posix() for p in written]
        assert steps == [(d, 4) for d in range(5)]  # 12 previews, every third: 4, progress over the share
    assert sorted(names) == sorted(ref) and len(set(names)) == len(names)
    assert _pngs(folder) == ref
    with pytest.raises(ValueError, match="share"):
        preview.write_run_previews(folder, share=(3, 3))


def _gone(pid, wait_s: float = 10.0) -> bool:
    """Process ``pid`` has ended within ``wait_s`` (a zombie waiting for its parent counts as ended)."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with open(f"/proc/{pid}/stat") as stat:
                if stat.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except OSError:
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)


def test_workers_draw_the_same_bytes_as_in_process(gated_run, tmp_path):
    src, ref = gated_run
    folder = _copy(src, tmp_path / "pool")
    seen = []
    with PreviewPool.start(2) as pool:
        assert len(pool.live()) == 1, pool.notes
        todo = pool.draw([folder], progress=lambda i, done: seen.append((i, done)))
        drawers = pool.workers[0].drawers
        pids = pool.pids + list(drawers.values())
    assert todo == []
    assert sorted(drawers) == [0, 1] and drawers[0] == pids[0] != drawers[1]  # the worker and a forked copy
    assert _pngs(folder) == ref
    assert not _hidden(folder)
    assert seen[-1] == (0, 12) and [d for _, d in seen] == sorted(d for _, d in seen)  # every preview counted once
    assert all(_gone(pid) for pid in pids)  # closed: the worker exited and was reaped, the drawer ended


def test_a_worker_killed_mid_draw_leaves_its_share_to_the_caller(gated_run, tmp_path):
    """SIGKILL of the worker at the first preview drawn: its forked drawer dies with it (PR_SET_PDEATHSIG), draw()
    returns the worker's share and a note; the caller draws it (preview.write_run_previews with that share) and
    the folder holds the same PNGs as an in-process draw, no temporary file of the killed processes."""
    src, ref = gated_run
    folder = _copy(src, tmp_path / "killed")
    notes = []
    with PreviewPool.start(2) as pool:
        assert len(pool.live()) == 1, pool.notes
        victim = pool.workers[0]

        def progress(i, done):
            if victim.proc.poll() is None:
                os.kill(victim.pid, signal.SIGKILL)

        todo = pool.draw([folder], progress=progress, note=notes.append)
        drawers = list(victim.drawers.values())
    assert [(f.name, share) for f, share in todo] == [("killed", (0, 1))]
    assert len(notes) == 1 and notes[0].startswith("preview worker 1 of 1 stopped (it exited (code -9))")
    assert all(_gone(pid) for pid in drawers)
    for f, share in todo:
        preview.write_run_previews(f, share=share)
    assert _pngs(folder) == ref
    assert not _hidden(folder)


def test_a_drawer_killed_mid_draw_leaves_its_share_to_its_worker(gated_run, tmp_path):
    """SIGKILL of the forked drawer at its first preview: the worker draws that drawer's share itself; the caller
    gets nothing to do and no note, and the folder holds the in-process PNGs, no temporary file."""
    src, ref = gated_run
    folder = _copy(src, tmp_path / "drawer")
    notes, killed = [], []
    with PreviewPool.start(2) as pool:
        worker = pool.workers[0]

        def progress(i, done):
            if 1 in worker.drawers and not killed:
                os.kill(worker.drawers[1], signal.SIGKILL)
                killed.append(worker.drawers[1])

        todo = pool.draw([folder], progress=progress, note=notes.append)
    assert killed and todo == [] and notes == []
    assert _pngs(folder) == ref
    assert not _hidden(folder)


def test_cancel_kills_the_workers(gated_run, tmp_path):
    src, _ = gated_run
    folder = _copy(src, tmp_path / "cancelled")
    with PreviewPool.start(2) as pool:
        assert len(pool.live()) == 1, pool.notes
        seen = []
        with pytest.raises(Cancelled):
            pool.draw([folder], progress=lambda i, d: seen.append(d), cancel=lambda: bool(seen))
        assert all(w.proc.poll() is not None for w in pool.workers)  # killed and reaped before the exception
        assert all(_gone(pid) for pid in pool.workers[0].drawers.values())
        assert pool.live() == []
        notes = []
        assert pool.draw([folder], note=notes.append) == [(folder.absolute(), (0, 1))]  # all to the caller
        assert len(notes) == 1 and notes[0].startswith("no preview worker is running (it exited (code -9)")


def test_a_worker_that_dies_before_drawing_leaves_everything_to_the_caller(gated_run, tmp_path):
    """A worker gone before the run's folder is ready (killed here; a package missing from its Python would end
    it the same way): one note, and the caller draws every preview."""
    src, _ = gated_run
    folder = _copy(src, tmp_path / "dead")
    with PreviewPool.start(2) as pool:
        os.kill(pool.workers[0].pid, signal.SIGKILL)
        pool.workers[0].proc.wait()
        notes = []
        assert pool.draw([folder], note=notes.append) == [(folder.absolute(), (0, 1))]
    assert notes == ["no preview worker is running (it exited (code -9) before drawing); the previews are drawn "
                     "here"]


def test_worker_count_from_the_environment(monkeypatch):
    for text, n in (("", None), ("0", 0), ("1", 1), ("3", 3), ("x", None), ("-4", 0), ("99", 8)):
        monkeypatch.setenv("LADAR_PREVIEW_WORKERS", text)
        assert worker_count() == n
    monkeypatch.setenv("LADAR_PREVIEW_WORKERS", "0")
    assert PreviewPool.start().workers == []


def test_default_starts_a_worker_only_where_a_core_is_idle(monkeypatch):
    """Without LADAR_PREVIEW_WORKERS: 2 drawers (at most the CPU count) where a core is idle, else no worker."""
    from core.fileio import preview_worker

    monkeypatch.delenv("LADAR_PREVIEW_WORKERS", raising=False)
    monkeypatch.setattr(preview_worker, "idle_cores", lambda: 0.0)
    assert preview_worker.default_drawers() == 0 and PreviewPool.start().workers == []
    monkeypatch.setattr(preview_worker, "idle_cores", lambda: 1.0)
    assert preview_worker.default_drawers() == min(2, os.cpu_count())
    # /proc/loadavg's runnable count includes the reader: on an idle machine one core's worth is taken
    assert preview_worker.idle_cores() <= os.cpu_count() - 1

"""Sweeps from Blender: ``blender -c ladar sweep`` (through the command handler), the threaded SweepJob that the
modal operator and the status bar use, and resuming; the workers are real dask.distributed worker processes."""
import csv
import json

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_plate

pytest.importorskip("distributed")


@pytest.fixture
def plate_scene(scene):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=2.0, location=(0, 0, -100))
    return scene


def _sweep_file(tmp_path, axes='"laser.pulse_energy_j" = [1e-4, 1e-3]\n"sensor.range_m" = [90.0, 110.0]\n'):
    f = tmp_path / "sweep.toml"
    f.write_text('sweep_version = 1\nseed = 3\n[settings]\nrun = { save_waveforms = false }\n'
                 'gate = { gate_start_s = 4e-7, n_bins = 1024 }\n[axes]\n' + axes, encoding="utf-8")
    return f


@pytest.fixture
def record_plots(lad, monkeypatch):
    """``record_plots()``: from then on the sweeps of this process record their plots (file name, axis, figure)
    instead of drawing them (0.2 s of CPU each).  Sweeps draw for real in this process in
    :func:`test_sweep_command_runs_every_point_then_resumes` (its first command, in the main thread) and in
    :func:`test_threaded_sweep_job_reports_progress_for_the_status_bar` (in a worker thread, as from the GUI); the
    drawing itself is tested in tests/core/sweep/test_sweep.py and, through scripts/ladar_run.py, in
    tests/addon/test_sweep_example.py."""
    import importlib
    from pathlib import Path

    runner = importlib.import_module(f"{lad.package.__name__}.core.sweep.runner")
    recorded = []

    def record(path, series, *, xlabel, ylabel, **kwargs):
        assert series  # what the drawing would refuse
        recorded.append((Path(path).name, xlabel, ylabel))
        return Path(path)

    def start():
        monkeypatch.setattr(runner, "sweep_plot_png", record)
        return recorded

    return start


def _run(lad, capsys, *argv):
    code = lad.cli.cli_handler(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_sweep_command_runs_every_point_then_resumes(lad, plate_scene, tmp_path, capsys, record_plots):
    out_dir = tmp_path / "sw"
    code, out, err = _run(lad, capsys, "sweep", str(_sweep_file(tmp_path)), "--out", str(out_dir), "--workers", "2")
    assert code == 0, err
    assert "4/4 done, 0 failed; 4 run now on 2 worker(s)" in out and "ladar: sweep" in out
    rows = _rows(out_dir / "results.csv")
    assert [r["status"] for r in rows] == ["done"] * 4
    by_range = {float(r["sensor.range_m"]): r for r in rows if float(r["laser.pulse_energy_j"]) == 1e-3}
    assert int(by_range[90.0]["pixels_with_echo"]) == 64  # the plate fills the field of view at both ranges
    # the echo moves with the sensor: 90 m and 110 m from the plate (boresight point at −100 m on the axis)
    for r_m, row in by_range.items():
        meta = json.loads((out_dir / row["run"] / "metadata.json").read_text())
        assert meta["sweep"]["values"]["sensor.range_m"] == r_m
        pts = np.load(out_dir / row["run"] / "points.npz")
        assert np.median(pts["range_m"]) == pytest.approx(r_m, abs=0.05)
    scene_meta = json.loads((out_dir / "scene" / "scene.json").read_text())
    assert scene_meta["info"]["sensor"] == "Ladar" and scene_meta["info"]["geometry_exports"] == 1
    drawn = sorted(p.name for p in (out_dir / "plots").glob("*.png"))
    assert drawn and all(p.stat().st_size > 1000 for p in (out_dir / "plots").glob("*.png"))
    # the same command again: nothing is run, the table is the same, the same plots are drawn again (recorded)
    table = (out_dir / "results.csv").read_text()
    plots = record_plots()
    code, out, err = _run(lad, capsys, "sweep", str(_sweep_file(tmp_path)), "--out", str(out_dir))
    assert code == 0, err
    assert "0 run now" in out and "4 finished before" in out
    assert (out_dir / "results.csv").read_text() == table
    assert sorted(name for name, _, _ in plots) == drawn
    # the scene changed: refused, unless --restart
    plate_scene.objects["Plate"].location.z = -105.0
    code, out, err = _run(lad, capsys, "sweep", str(_sweep_file(tmp_path)), "--out", str(out_dir))
    assert code == 1 and "the scene changed" in err and "--restart" in err
    assert (out_dir / "results.csv").read_text() == table


def test_bad_axis_value_names_the_field_and_writes_nothing(lad, plate_scene, tmp_path, capsys):
    f = _sweep_file(tmp_path, axes='"atmosphere.visibility_m" = [1000, 10]\n')
    code, _, err = _run(lad, capsys, "sweep", str(f), "--out", str(tmp_path / "sw"))
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1
    assert lines[0].startswith("ladar: error: atmosphere.visibility_m = 10.0 is not allowed: 0 (off) or a "
                               "visibility in [50, 1e+06] m (sweep point 1")
    assert not (tmp_path / "sw").exists()


def test_threaded_sweep_job_reports_progress_for_the_status_bar(lad, plate_scene, tmp_path):
    import importlib
    sweep = importlib.import_module(f"{lad.package.__name__}.ladar_addon.sweep")
    job = sweep.SweepJob(plate_scene, _sweep_file(tmp_path, axes='"laser.pulse_energy_j" = [1e-4, 1e-3, 1e-2]\n'),
                         tmp_path / "sw", n_workers=1)
    assert job.n_tasks == 3 and job.status_text() == "Ladar sweep sw: 3 tasks"
    seen = []
    job.user_progress = lambda f, t: seen.append(t)
    lad.job.set_current_job(job)
    try:
        job.start(threaded=True)
        assert lad.job.current_job() is job  # the status bar draws it
        assert job.wait(timeout_s=300)
    finally:
        lad.job.set_current_job(None)
    assert job.state == "done", job.error
    assert seen[-1].startswith("3/3 tasks") and job.fraction == 1.0
    assert job.summary().startswith("sweep: 3/3 tasks done, 0 failed")
    assert list((tmp_path / "sw" / "plots").glob("*.png"))  # drawn in the job's thread
    assert bpy.context.scene.ladar.last_run == str(tmp_path / "sw")


def _one_error_line(err, start):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(start), err
    assert "Traceback" not in err


@pytest.mark.parametrize("address", ["nonsense", "tcp://127.0.0.1", "tcp://127.0.0.1:99999", "udp://host:8786"])
def test_a_malformed_scheduler_address_is_one_line_before_anything(lad, plate_scene, tmp_path, capsys, address):
    code, out, err = _run(lad, capsys, "sweep", str(_sweep_file(tmp_path)), "--out", str(tmp_path / "sw"),
                          "--scheduler", address)
    assert code == 1
    _one_error_line(err, f"ladar: error: scheduler = {address!r} is not allowed: a Dask scheduler's address "
                         f"tcp://HOST:PORT")
    assert not (tmp_path / "sw").exists() and "ladar: sweep" not in out


@pytest.mark.parametrize("banner, words", [(b"SSH-2.0-OpenSSH_9.2p1\r\n", "its first message claims"),
                                           (b"HTTP/1.1 400 Bad Request\r\n\r\n", "its first message claims")])
def test_a_scheduler_address_where_another_service_answers_is_one_line(lad, plate_scene, tmp_path, capsys, banner,
                                                                       words):
    import socket
    import threading

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    srv.settimeout(30)

    def serve():
        try:
            conn, _ = srv.accept()
            conn.sendall(banner)
            conn.recv(1)  # until the client leaves
            conn.close()
        except OSError:
            pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        code, out, err = _run(lad, capsys, "sweep", str(_sweep_file(tmp_path)), "--out", str(tmp_path / "sw"),
                              "--scheduler", f"tcp://127.0.0.1:{srv.getsockname()[1]}")
    finally:
        srv.close()
        thread.join(5)
    assert code == 1
    _one_error_line(err, "ladar: error: scheduler = ")
    assert words in err and "not a Dask scheduler" in err
    assert not (tmp_path / "sw").exists()


def test_frames_of_a_sweep_file_are_simulated_each(lad, plate_scene, tmp_path, capsys, record_plots):
    """``frames = 99999`` is frame 99999 (the plate is keyed 100 m away at frame 1 and 150 m at frame 99999): its
    echo is at 150 m, the table says frame 99999 and the first line names it; ``frames = [1, 99999]`` is two tasks
    per point, one per frame."""
    plots = record_plots()  # (each sweep's plots recorded, not drawn: see record_plots)
    plate = plate_scene.objects["Plate"]
    plate.location.z = -100.0
    plate.keyframe_insert("location", frame=1)
    plate.location.z = -150.0
    plate.keyframe_insert("location", frame=99999)
    for frames, expect in (("99999", {99999: 150.0}), ("[1, 99999]", {1: 100.0, 99999: 150.0})):
        f = tmp_path / f"frames{len(expect)}.toml"
        f.write_text(f'sweep_version = 1\nseed = 3\nframes = {frames}\n[settings]\nrun = {{ save_waveforms = false }}'
                     '\ngate = { gate_start_s = 4e-7, n_bins = 1024 }\n[axes]\n"laser.pulse_energy_j" = [1e-3]\n',
                     encoding="utf-8")
        out_dir = tmp_path / f"sw{len(expect)}"
        code, out, err = _run(lad, capsys, "sweep", str(f), "--out", str(out_dir), "--workers", "1")
        assert code == 0, err
        shown = ", ".join(str(k) for k in expect)
        assert (f"{len(expect)} tasks (1 points × 1 seeds × frame{'s' if len(expect) > 1 else ''} {shown})"
                in out), out
        rows = _rows(out_dir / "results.csv")
        assert sorted(int(r["frame"]) for r in rows) == sorted(expect)
        for r in rows:
            frame = int(r["frame"])
            meta = json.loads((out_dir / r["run"] / "metadata.json").read_text())
            assert meta["frame"] == frame
            pts = np.load(out_dir / r["run"] / "points.npz")
            assert np.median(pts["range_m"]) == pytest.approx(expect[frame], abs=0.05)
    assert plots and all(axis == "laser.pulse_energy_j" for _, axis, _ in plots)

"""The modal simulate path without a window: a worker thread driven by SimulationJob.step (the operator's timer),
ESC/cancel within a second leaving nothing behind, failures reported, the operator's modal() on stand-ins."""
import time
import types

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_plate


def _scene(scene, tmp_path, width=64, subsamples=2):
    cam = add_camera(scene, width_px=width, height_px=width, fov_rad=0.004)
    cam.ladar.receiver.subsamples = subsamples
    cam.ladar.run.chunk_rays = 1024  # many small blocks: the core checks for cancellation before each
    cam.ladar.run.threads = 1
    add_plate(scene, size=4.0, location=(0, 0, -100))
    scene.ladar.output_dir = str(tmp_path / "runs")
    return cam


def _snapshot():
    return (set(bpy.data.objects.keys()), set(bpy.data.images.keys()), set(bpy.data.meshes.keys()),
            set(bpy.data.collections.keys()))


@pytest.mark.parametrize("frames", [None, [1, 2, 3, 4, 5, 6]])
def test_cancel_mid_run_within_a_second_leaves_nothing(lad, scene, tmp_path, frames):
    _scene(scene, tmp_path)
    scene.frame_set(4)
    before = _snapshot()
    job = lad.job.SimulationJob(scene, frames=frames, frame=None if frames else 4)
    job.start(threaded=True)
    t0 = time.perf_counter()
    while job.fraction == 0.0 and not job.finished:  # the core has started
        job.step()
        time.sleep(0.002)
        assert time.perf_counter() - t0 < 60
    assert not job.finished
    job.cancel()
    t_cancel = time.perf_counter()
    while not job.step():
        time.sleep(0.005)
    stop_s = time.perf_counter() - t_cancel
    assert job.state == "cancelled" and stop_s < 1.0, stop_s
    assert not (tmp_path / "runs").exists()   # no run, no staging folder, not even the parent it created
    assert _snapshot() == before               # no objects, images, meshes or collections
    assert scene.frame_current == 4
    assert "cancel" in job.text


def test_step_serves_frames_and_imports_on_the_main_thread(lad, scene, tmp_path):
    _scene(scene, tmp_path, width=16, subsamples=1)
    job = lad.job.SimulationJob(scene, frames=[1, 2, 3])
    job.start(threaded=True)
    n_steps = 0
    while not job.step():
        n_steps += 1
        time.sleep(0.01)
        assert n_steps < 6000
    assert job.state == "done" and job.fraction == 1.0
    assert job.source.exports == 1  # static: exported once, in the constructor (main thread)
    obj = bpy.data.objects["Ladar_f0001-0003"]
    assert len(obj.data.vertices) == 3 * 256
    assert job.max_step_s < 0.5  # each main-thread step is short (the interface stays responsive)
    assert lad.job.current_job() is None


def test_worker_failure_is_reported_and_writes_nothing(lad, scene, tmp_path):
    _scene(scene, tmp_path, width=8, subsamples=1)
    plate = bpy.data.objects["Plate"]
    plate.keyframe_insert("location", frame=1)
    plate.location.x = 500.0  # out of view at frame 3
    plate.keyframe_insert("location", frame=3)
    before = _snapshot()
    job = lad.job.SimulationJob(scene, frames=[1, 2, 3])
    job.start(threaded=True)
    assert job.wait(timeout_s=60)
    assert job.state == "failed"
    assert "sees nothing" in job.summary()
    assert not (tmp_path / "runs").exists() and _snapshot() == before
    assert scene.frame_current == 1


def test_modal_event_handling(lad, scene, tmp_path):
    _scene(scene, tmp_path, width=16, subsamples=1)
    handle = lad.job.handle_modal_event
    job = lad.job.SimulationJob(scene)
    job.start(threaded=True)
    assert handle(job, "MOUSEMOVE", "NOTHING") == "PASS_THROUGH"  # the interface keeps its events
    status = "PASS_THROUGH"
    for _ in range(6000):
        status = handle(job, "TIMER")
        if status != "PASS_THROUGH":
            break
        time.sleep(0.01)
    assert status == "FINISHED" and bpy.data.objects.get("Ladar_f0001") is not None

    job = lad.job.SimulationJob(scene, out_dir=tmp_path / "esc")
    job.start(threaded=True)
    assert handle(job, "ESC", "PRESS") == "RUNNING_MODAL" and job.cancelled_requested()
    assert "cancelling" in job.status_text()
    for _ in range(6000):
        status = handle(job, "TIMER")
        if status != "PASS_THROUGH":
            break
        time.sleep(0.01)
    assert status == "CANCELLED" and job.state == "cancelled"
    assert not (tmp_path / "esc").exists() and bpy.data.objects.get("esc") is None


def _run_modal_on_stand_ins(op_cls, job, ctx):
    """Drive ``op_cls.modal`` with a stand-in operator (the operator's own ``_end``, ``cancelled_text`` and
    texts) and TIMER events until the job ends: (the last status, the reports in order)."""
    reports = []
    op = types.SimpleNamespace(_job_ref=job, _timer="timer", report=lambda kind, msg: reports.append((kind, msg)))
    for name in ("_end", "cancelled_text"):  # the stand-in gets the operator's own methods and texts
        setattr(op, name, types.MethodType(getattr(op_cls, name), op))
    op.FINISHED_PREFIX = op_cls.FINISHED_PREFIX
    timer = types.SimpleNamespace(type="TIMER", value="NOTHING")
    result = {"PASS_THROUGH"}
    for _ in range(6000):
        result = op_cls.modal(op, ctx, timer)
        if result != {"PASS_THROUGH"}:
            break
        time.sleep(0.01)
    return result, reports


def test_operator_modal_on_stand_ins(lad, scene, tmp_path):
    """The operator's modal()/_end() with a stand-in operator, context and events (no window needed)."""
    _scene(scene, tmp_path, width=8, subsamples=1)
    op_cls = lad.package.operators.simulate.LADAR_OT_simulate
    removed = []
    wm = types.SimpleNamespace(windows=[], event_timer_remove=removed.append)
    ctx = types.SimpleNamespace(window_manager=wm)
    job = lad.job.SimulationJob(scene)
    job.start(threaded=True)
    lad.job.set_current_job(job)
    assert not op_cls.poll(types.SimpleNamespace(scene=scene))  # one run at a time
    result, reports = _run_modal_on_stand_ins(op_cls, job, ctx)
    assert result == {"FINISHED"}
    assert removed == ["timer"] and lad.job.current_job() is None
    assert reports and reports[-1][0] == {"INFO"} and "64 points" in reports[-1][1]
    assert op_cls.poll(types.SimpleNamespace(scene=scene))


def test_background_operator_prints_progress(lad, scene, tmp_path, capsys):
    _scene(scene, tmp_path, width=8, subsamples=1)
    assert bpy.app.background
    assert bpy.ops.ladar.simulate("INVOKE_DEFAULT", frames="1-2") == {"FINISHED"}  # synchronous in background
    out = capsys.readouterr().out
    assert "ladar: 100.0%" in out and "frame 2 (2/2)" in out and "ladar: wrote" in out
    assert len(bpy.data.objects["Ladar_f0001-0002"].data.vertices) == 128


def test_invoke_runs_modally_with_a_window(lad, scene, tmp_path, monkeypatch):
    """invoke() as the interface calls it (a window, not background): job started, timer and modal handler
    added, status shown; then modal() on TIMER events until FINISHED, timer removed, one run at a time."""
    _scene(scene, tmp_path, width=8, subsamples=1)
    op_module = lad.package.operators.simulate
    monkeypatch.setattr(op_module, "bpy", types.SimpleNamespace(app=types.SimpleNamespace(background=False),
                                                                data=bpy.data))
    calls = []
    wm = types.SimpleNamespace(windows=[], event_timer_add=lambda dt, window: calls.append(("timer", dt)) or "T",
                               modal_handler_add=lambda op: calls.append(("modal", op)),
                               event_timer_remove=lambda t: calls.append(("remove", t)))
    ctx = types.SimpleNamespace(scene=scene, window="W", window_manager=wm)
    reports = []
    op = types.SimpleNamespace(sensor="", frames="1-2", report=lambda kind, msg: reports.append((kind, msg)))
    for name in ("_job", "_end", "_watch", "cancelled_text"):
        setattr(op, name, types.MethodType(getattr(op_module.LADAR_OT_simulate, name), op))
    op.FINISHED_PREFIX = op_module.LADAR_OT_simulate.FINISHED_PREFIX
    assert op_module.LADAR_OT_simulate.invoke(op, ctx, None) == {"RUNNING_MODAL"}
    assert calls[:2] == [("timer", 0.1), ("modal", op)]
    job = lad.job.current_job()
    assert job is op._job_ref and job.sequence and job.frames == [1, 2]
    assert _status(lad)[0][0] == "progress"
    timer = types.SimpleNamespace(type="TIMER", value="NOTHING")
    for _ in range(6000):
        result = op_module.LADAR_OT_simulate.modal(op, ctx, timer)
        if result != {"PASS_THROUGH"}:
            break
        time.sleep(0.01)
    assert result == {"FINISHED"} and calls[-1] == ("remove", "T")
    assert lad.job.current_job() is None and _status(lad) == []
    assert (tmp_path / "runs" / "Ladar_f0001-0002" / "metadata.json").is_file()
    # a user error is reported by invoke and nothing starts
    op.frames = "2-1"
    assert op_module.LADAR_OT_simulate.invoke(op, ctx, None) == {"CANCELLED"}
    assert reports[-1][0] == {"ERROR"} and "frames" in reports[-1][1] and lad.job.current_job() is None


def _status(lad):
    from test_panels import RecordingLayout
    log = []
    lad.package.panels.status.draw_status(types.SimpleNamespace(layout=RecordingLayout(log)), None)
    return log


def test_a_folder_created_during_the_run_is_not_replaced(lad, scene, tmp_path):
    _scene(scene, tmp_path, width=32, subsamples=2)
    job = lad.job.SimulationJob(scene, frames=[1, 2, 3], out_dir=tmp_path / "runs" / "taken")
    job.start(threaded=True)
    (tmp_path / "runs" / "taken").mkdir(parents=True)
    (tmp_path / "runs" / "taken" / "mine.txt").write_text("keep")
    assert job.wait(timeout_s=60) and job.state == "failed"
    assert "created by someone else" in job.summary()
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["taken"]
    assert [p.name for p in (tmp_path / "runs" / "taken").iterdir()] == ["mine.txt"]


def test_operator_warns_when_the_range_gate_misses_the_scene(lad, scene, tmp_path):
    """A plate at 400 m, the default gate 0–307 m: the run finishes with 0 points and the operator reports a
    WARNING naming the gate, the hits' range and the settings that cover them (as metadata.json does)."""
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    cam.ladar.run.threads = 1
    add_plate(scene, size=8.0, location=(0, 0, -400))
    scene.ladar.output_dir = str(tmp_path / "runs")
    op_cls = lad.package.operators.simulate.LADAR_OT_simulate
    wm = types.SimpleNamespace(windows=[], event_timer_remove=lambda t: None)
    ctx = types.SimpleNamespace(window_manager=wm)
    job = lad.job.SimulationJob(scene)
    job.start(threaded=True)
    lad.job.set_current_job(job)
    result, reports = _run_modal_on_stand_ins(op_cls, job, ctx)
    assert result == {"FINISHED"}
    assert reports[0][0] == {"INFO"} and "0 points" in reports[0][1]
    assert [k for k, _ in reports[1:]] == [{"WARNING"}]
    text = reports[1][1]
    assert text.startswith("Ladar: range gate: only 0.0 % of the hit energy") and "0.0–307.0 m" in text
    assert "the hits are at 400.0–400.0 m" in text and "gate.gate_start_s" in text and "gate.n_bins" in text
    import json
    meta = json.loads((job.run_path / "metadata.json").read_text())
    assert meta["warnings"] == [text.removeprefix("Ladar: ")]

"""Compiling the kernels ahead from Blender: ``bpy.ops.ladar.warm_up`` / WarmUpJob runs core/warmup.py's cases on
a worker thread with a progress line and fraction, stops between cases on cancel (no 'warm' marker then), and
leaves the marker when every case ran; the sensor panel offers it only while the marker is missing.  The cases are
cut to two tiny ones here (the full warm-up's coverage is tests/addon/test_cli.py's)."""
import importlib

import bpy
import pytest


@pytest.fixture
def tiny(lad, monkeypatch, tmp_path):
    pkg = lad.job.__name__.rpartition(".ladar_addon")[0]
    core_warmup = importlib.import_module(f"{pkg}.core.warmup")
    addon_warmup = importlib.import_module(f"{pkg}.ladar_addon.warmup")
    few = core_warmup.cases()[:2]
    monkeypatch.setattr(core_warmup, "cases", lambda: few)
    monkeypatch.setattr(addon_warmup, "cases", lambda: few)
    monkeypatch.setattr(core_warmup, "marker", lambda: tmp_path / "WARM")
    return core_warmup, addon_warmup, tmp_path / "WARM"


def test_warm_up_job_reports_progress_and_marks_the_cache(tiny):
    core_warmup, addon_warmup, marker = tiny
    assert not core_warmup.is_warm()
    job = addon_warmup.WarmUpJob()
    assert job.total == 2 and job.fraction == 0.0
    job.start(threaded=True)
    assert job.wait(timeout_s=600) and job.state == "done", job.summary()
    assert job.fraction == 1.0 and "[2/2]" in job.status_text()
    assert job.summary().startswith("kernels ready:")
    assert marker.is_file() and core_warmup.is_warm()


def test_a_cancelled_warm_up_stops_between_cases_and_leaves_no_marker(tiny):
    core_warmup, addon_warmup, marker = tiny
    job = addon_warmup.WarmUpJob()
    job.cancel()  # before the first case: nothing runs
    job.start(threaded=True)
    assert job.wait(timeout_s=600) and job.state == "cancelled"
    assert job.fraction == 0.0 and not marker.exists()


def test_the_operator_in_background_mode_runs_to_the_end(tiny):
    core_warmup, addon_warmup, marker = tiny
    assert bpy.ops.ladar.warm_up() == {"FINISHED"}
    assert marker.is_file()

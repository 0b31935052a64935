"""Sweeps started from Blender: export the scene once, then run the sweep on Dask (``core.sweep.runner``).

    blender -b scene.blend -c ladar sweep sweep.toml --out DIR [--scheduler tcp://host:8786] [--workers N]
                                                            [--restart] [--sensor NAME]

A :class:`SweepJob` reads everything from Blender on the main thread — the settings (the .blend's, then the sweep
file's ``base`` config file, exactly as ``simulate --config``), and for every frame of the sweep the evaluated
geometry with its materials, the sensor pose and, for a scanner on an animated sensor, its trajectory (the
frame-range machinery of :mod:`.frames`: static geometry is exported once) — into a ``core.sweep``
SweepScene.  Then the sweep runs without Blender data, inline (scripts, background mode: progress lines) or in a
worker thread while the modal operator polls :meth:`SweepJob.step` (the status bar shows done/total and the ETA;
ESC cancels: finished points are kept and the same command resumes).  The workers are plain Python processes
with the core and the pinned packages of ``requirements-worker.txt``; nothing of Blender runs on them.
"""
from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import bpy

from ..core.errors import Cancelled
from ..core.sweep.runner import check_workers, plan_sweep, run_sweep, scheduler_address
from ..core.sweep.scene import SweepScene
from ..core.sweep.spec import load_sweep
from .background import BackgroundJob
from .errors import LadarError
from .blend_config import unit_scale
from .frames import FrameSource
from .run_inputs import active_sensor, build_config


def export_sweep_scene(scene, sensor, cfg, blender_materials, frames) -> SweepScene:
    """The geometry, materials, poses and trajectories of ``frames`` (main thread; the scene returns to its
    current frame).  Geometry that does not change is exported once and shared by the frames."""
    original = scene.frame_current
    source = FrameSource(scene, sensor, cfg, blender_materials, unit_scale(scene))
    geometries, index_of, geometry_of_frame, poses, trajs, starts = [], {}, [], [], [], []
    try:
        for f in frames:
            inputs = source.prepare(f)
            key = id(inputs.geometry)
            if key not in index_of:
                index_of[key] = len(geometries)
                geometries.append(inputs.geometry)
            geometry_of_frame.append(index_of[key])
            poses.append(inputs.world_from_sensor)
            trajs.append(inputs.trajectory)
            starts.append(inputs.start_time_s)
    finally:
        if scene.frame_current != original:
            scene.frame_set(original)
    info = {"blender": bpy.app.version_string, "file": bpy.data.filepath, "scene": scene.name,
            "sensor": sensor.name, "unit_scale_m": source.scale_m, "geometry_exports": source.exports,
            "time_dependent_objects": source.time_dependent}
    return SweepScene(geometries, list(frames), geometry_of_frame, poses, trajs, starts, info)


class SweepJob(BackgroundJob):
    """One sweep from set-up to the results table.  The constructor reads the sweep file, the settings and the
    scene and validates every point (raising ConfigError/LadarError before anything is written); then
    :meth:`run` (blocking) or :meth:`start` ``(threaded=True)`` + :meth:`step` from the main thread, the
    interface of :class:`.job.SimulationJob` (the modal operator and the status bar serve both).

    States: "ready" → "running" → "done" | "failed" (``error``) | "cancelled"."""

    def __init__(self, scene, sweep_file, out_dir, *, scheduler=None, n_workers=None, restart=False, sensor=None,
                 progress=None):
        self.scene = scene
        self.sensor = sensor if sensor is not None else active_sensor(scene)
        if scheduler:
            scheduler_address(scheduler)  # a malformed address: one line before the scene is exported
        check_workers(n_workers)
        spec = load_sweep(sweep_file)
        if out_dir is None or not str(out_dir):
            raise LadarError("no sweep folder: pass --out DIR")
        path = str(out_dir)
        if path.startswith("//"):
            if not bpy.data.filepath:
                raise LadarError(f"the sweep folder {path!r} is relative to the .blend file, which is not saved")
            path = bpy.path.abspath(path)
        self.out_dir = Path(path).expanduser().resolve()
        self.run_name = self.out_dir.name
        cfg, blender_materials = build_config(scene, self.sensor, config_path=spec.base)
        frames = spec.frames if spec.frames is not None else [scene.frame_current]
        self.sweep_scene = export_sweep_scene(scene, self.sensor, cfg, blender_materials, frames)
        # the base file is applied (build_config: the camera's field of view unless the file sets it); the
        # material overrides are in the exported geometry
        self.spec = dataclasses.replace(spec, base=None, frames=frames)
        self.base = dataclasses.replace(cfg, materials={})
        self.plan = plan_sweep(self.spec, self.sweep_scene, self.base, self.out_dir)  # every point validated now
        plan = self.plan
        self.n_tasks = len(plan.tasks)
        self.n_points = plan.manifest["n_points"]
        self.scheduler, self.n_workers, self.restart = scheduler, n_workers, restart
        self.user_progress = progress
        self.state, self.error, self.outcome = "ready", None, None
        self.fraction, self.text = 0.0, f"{self.n_tasks} tasks"
        self.t_start = self.t_end = None
        self._cancel = threading.Event()
        self._thread = None
        self._done = threading.Event()
        self._worker_error = None

    def cancel(self) -> None:
        """Stop submitting and cancel the running tasks; finished tasks stay (run the sweep again to resume)."""
        self._cancel.set()

    def _on_progress(self, fraction, text=""):
        self.fraction, self.text = float(fraction), str(text)
        if self.user_progress is not None:
            self.user_progress(fraction, text)

    def _work(self):
        try:
            self.outcome = run_sweep(self.spec, self.sweep_scene, self.out_dir, base=self.base,
                                     scheduler=self.scheduler, n_workers=self.n_workers, restart=self.restart,
                                     progress=self._on_progress, cancel=self._cancel.is_set,
                                     plan=self.plan)  # (validated once, in the constructor)
        except BaseException as exc:  # handed to the main thread by _finish
            self._worker_error = exc
        finally:
            self._done.set()

    def start(self, threaded: bool = True) -> None:
        if self.state != "ready":
            raise RuntimeError(f"the job is {self.state}")
        self.state = "running"
        self.t_start = time.perf_counter()
        if bpy.app.background:
            frames = self.spec.frames
            shown = ", ".join(str(f) for f in frames[:5]) + (f", … ({len(frames)} frames)" if len(frames) > 5 else "")
            print(f"ladar: sweep {self.spec.source}: {self.n_tasks} tasks ({self.n_points} points × {self.spec.seeds} "
                  f"seeds × frame{'s' if len(frames) > 1 else ''} {shown}) into {self.out_dir}", flush=True)
        if threaded:
            self._thread = threading.Thread(target=self._work, name="ladar-sweep", daemon=True)
            self._thread.start()
        else:
            self._work()
            self._finish()

    def run(self):
        """Run to the end in the calling thread.  Raises the sweep's error (Cancelled if cancelled)."""
        self.start(threaded=False)
        return self.raise_outcome()

    def step(self) -> bool:
        if self.finished:
            return True
        if self._done.is_set():
            self._thread.join()
            self._finish()
        return self.finished

    def _finish(self):
        self.t_end = time.perf_counter()
        exc = self._worker_error
        if isinstance(exc, (Cancelled, KeyboardInterrupt)):
            self.state, self.text = "cancelled", "cancelled (finished points kept)"
        elif exc is not None:
            self.state, self.error, self.text = "failed", exc, f"failed: {exc}"
        else:
            self.state, self.fraction, self.text = "done", 1.0, "done"
            try:
                self.scene.ladar.last_run = str(self.out_dir)
            except (AttributeError, ReferenceError):  # pragma: no cover
                pass

    def summary(self) -> str:
        if self.state == "done":
            o = self.outcome
            return f"sweep: {o.n_done}/{o.n_tasks} tasks done, {o.n_failed} failed, in {self.out_dir}"
        if self.state == "failed":
            return str(self.error) or type(self.error).__name__
        return self.state

    def status_text(self) -> str:
        if self._cancel.is_set() and not self.finished:
            return f"Ladar sweep {self.run_name}: cancelling…"
        return f"Ladar sweep {self.run_name}: {self.text}"


def sweep_scene(scene, sweep_file, out_dir, *, scheduler=None, n_workers=None, restart=False, sensor=None,
                progress=None):
    """Run a sweep of the scene's ladar sensor to the end (scripts); returns the ``core.sweep`` SweepOutcome.
    Raises ConfigError (a bad sweep file or point: nothing written) or LadarError (the scene)."""
    job = SweepJob(scene, sweep_file, out_dir, scheduler=scheduler, n_workers=n_workers, restart=restart,
                   sensor=sensor, progress=progress).run()
    return job.outcome


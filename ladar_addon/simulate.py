"""Simulate the scene's ladar sensor: export → settings → core → run folder → results in Blender.

Usable from scripts::

    from bl_ext.<repo>.ladar_simulator.ladar_addon.simulate import simulate_scene, simulate_sequence
    run_path, result = simulate_scene(bpy.context.scene, out_dir="/tmp/runs/r1", frame=1, seed=7)
    seq_path, frame_stats = simulate_sequence(bpy.context.scene, parse_frames("1-100"), out_dir="/tmp/runs/s1")

A run is a :class:`SimulationJob`.  Everything that reads Blender data happens on the main thread (export of the
evaluated depsgraph, the sensor pose, the sampled sensor trajectory); the core (ray tracing, waveforms, writing
files) runs either inline (scripts, background mode: progress lines are printed) or in a worker thread while the
modal operator calls :meth:`SimulationJob.step` from a timer (the interface stays responsive; ESC cancels).
For a frame sequence the worker runs ``core.sequence.run_sequence`` and asks the main thread for each frame's
inputs through a request that :meth:`~SimulationJob.step` serves.

Run folders (``out_dir`` is the folder itself):

* one frame: ``<Scene.ladar.output_dir>/<sensor>_f<frame:04d>`` by default — the products of
  ``core.run.run_simulation`` plus a false-colour PNG beside each EXR (``core.fileio.preview``);
* a frame range: ``<output_dir>/<sensor>_f<first>-<last>`` — ``core.sequence``'s ``frame_NNNN/`` run folders,
  ``points_merged.ply``/``.npz`` and ``metadata.json``, plus PNG previews in every frame folder and
  ``images/range_NNNN.exr`` … (hard links to the frames' images, numbered by scene frame) so that each product
  loads as one Blender image sequence.

The whole folder is assembled in a hidden staging folder beside it and renamed into place at the end: a failed
or cancelled run leaves no partial output, and results are imported into Blender only after that (an import
that fails removes what it created).  An existing run folder or result of the same name is never replaced
silently: ``if_exists`` = "STOP" refuses, "REPLACE" replaces it, "NEW" picks the next free name
(``<name>_2``, ``<name>_3`` …) and keeps the old one.

Static geometry is exported once and its ray-tracing BVH reused for every frame: objects that may change with
time are listed by ``export.frame_dependent_objects``; if there are any, each frame is re-exported and the BVH is
rebuilt only when the geometry's digest changes.  A scanner whose sensor object is animated gets the sensor's
pose sampled over the scan (sub-frames) as a ``core.geometry.motion.Trajectory``.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import threading
import time
from pathlib import Path

import bpy
import numpy as np

from ..core.errors import ConfigError
from ..core.version import __version__ as core_version
from ..core.config.settings import validate
from ..core.config.files import config_to_dict, load_config
from ..core.geometry.motion import Trajectory
from ..core.errors import Cancelled
from ..core.run import run_simulation
from ..core.fileio.staging import check_run_dir, claim_run_dir, free_run_path
from ..core.process import emit
from .errors import LadarError
from .export import frame_dependent_objects, geometry_digest, scene_geometry_from_depsgraph
from .blend_config import check_sensor, config_from_blender, unit_scale
from .results import check_result_names, existing_results, import_run
from .sensor import camera_receiver_fov_rad

IF_EXISTS = ("STOP", "REPLACE", "NEW")
CLOUDS = ("RUN", "FRAME")
#: Most sensor poses sampled per scan (each costs a scene evaluation on the main thread).
MAX_MOTION_SAMPLES = 1000
#: Poses per Blender frame that resolve the sensor's animation curves (finer sampling adds nothing).
MOTION_SAMPLES_PER_FRAME = 16


# ------------------------------------------------------------------------------------------------------------
# Names, folders, settings
# ------------------------------------------------------------------------------------------------------------
_FRAMES_ITEM = re.compile(r"^\s*(-?\d+)\s*(?:-\s*(-?\d+)\s*(?::\s*(\d+)\s*)?)?$")


def parse_frames(text) -> list[int]:
    """Frame numbers from "7", "1-100", "1-100:5" (every 5th) or a comma list such as "1,4,10-12".

    Raises ConfigError (field ``frames``) for anything else, an empty or reversed range, or a repeated frame.
    """
    allowed = 'frame numbers such as "7", "1-100", "1-100:5" (every 5th) or "1,4,10-12"'
    frames = []
    for item in str(text).split(","):
        m = _FRAMES_ITEM.match(item)
        if m is None:
            raise ConfigError("frames", text, allowed)
        first = int(m.group(1))
        last = int(m.group(2)) if m.group(2) is not None else first
        step = int(m.group(3)) if m.group(3) is not None else 1
        if last < first or step < 1:
            raise ConfigError("frames", text, allowed + " (first ≤ last, step ≥ 1)")
        frames.extend(range(first, last + 1, step))
    if len(set(frames)) != len(frames):
        raise ConfigError("frames", text, "each frame once")
    return frames


def active_sensor(scene):
    """The scene's ladar sensor: ``Scene.ladar.sensor``, else the scene camera.  Raises LadarError."""
    sensor = scene.ladar.sensor or scene.camera
    if sensor is None:
        raise LadarError("no ladar sensor: set Scene > Ladar > Sensor or the scene camera to a camera object")
    check_sensor(sensor)
    return sensor


def default_run_name(sensor, frame: int, last_frame: int | None = None) -> str:
    """``<sensor>_f0001`` for one frame, ``<sensor>_f0001-0100`` for a frame sequence."""
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", sensor.name).strip("._") or "sensor"
    return f"{name}_f{frame:04d}" + (f"-{last_frame:04d}" if last_frame is not None else "")


def resolve_run_dir(scene, sensor, frame: int, out_dir=None, last_frame: int | None = None) -> Path:
    """The absolute run folder: ``out_dir``, else ``<Scene.ladar.output_dir>/<default_run_name>``.

    A path starting with ``//`` is relative to the .blend file, which must then be saved.
    """
    if out_dir is not None:
        path = str(out_dir)
    else:
        if not scene.ladar.output_dir:
            raise LadarError("no output folder: set Scene > Ladar > Output Folder or pass --out")
        base = scene.ladar.output_dir
        path = base + ("" if base.endswith(("/", "\\")) else "/") + default_run_name(sensor, frame, last_frame)
    if not path:
        raise LadarError("no run folder given")
    if path.startswith("//"):
        if not bpy.data.filepath:
            raise LadarError(f"the output folder {path!r} is relative to the .blend file, which is not saved: "
                             f"save it or choose an absolute folder")
        path = bpy.path.abspath(path)
    return Path(path).expanduser().resolve()


def _file_keys(config_path) -> dict:
    """The raw top-level tables of a config file (to tell which settings it sets explicitly)."""
    path = Path(config_path)
    try:
        if path.suffix.lower() == ".toml":
            import tomllib
            return tomllib.loads(path.read_text(encoding="utf-8"))
        return json.loads(path.read_text(encoding="utf-8"))
    except Exception:  # load_config reports the error properly
        return {}


def build_config(scene, sensor, *, config_path=None, seed=None):
    """The run's settings: the .blend's, then the config file's, then ``seed``.  Validated.

    The receiver field of view follows the camera for the final receiver size, unless the config file sets
    ``receiver.fov_x_rad``/``fov_y_rad`` itself.  Returns (config, the .blend's material table).
    """
    cfg = config_from_blender(scene, sensor)
    blender_materials = dict(cfg.materials)
    if config_path is not None:
        cfg = load_config(config_path, base=cfg)
        receiver = _file_keys(config_path).get("receiver", {})
        if not isinstance(receiver, dict) or not ({"fov_x_rad", "fov_y_rad"} & set(receiver)):
            rx = cfg.receiver
            rx.fov_x_rad, rx.fov_y_rad = camera_receiver_fov_rad(sensor.data, rx.width_px, rx.height_px)
    if seed is not None:
        cfg.run.seed = int(seed)
    validate(cfg)
    return cfg, blender_materials


def progress_printer(prefix="ladar: "):
    """A progress callback that prints a line at most every 10 % (background mode: Blender draws nothing)."""
    state = {"next": 0.0, "t0": time.perf_counter(), "lock": threading.Lock()}

    def progress(fraction, message=""):
        with state["lock"]:
            if fraction + 1e-9 >= state["next"] or fraction >= 1.0:
                emit(f"{prefix}{100 * fraction:5.1f}% {message} ({time.perf_counter() - state['t0']:.2f} s)")
                state["next"] = min(1.0, fraction + 0.1)
    return progress


def _log(message):
    if bpy.app.background:
        emit(f"ladar: {message}")


def print_error(message: str) -> None:
    emit(f"ladar: error: {message}", err=True)


# ------------------------------------------------------------------------------------------------------------
# Per-frame inputs (main thread)
# ------------------------------------------------------------------------------------------------------------
def scene_time_s(scene, frame: float) -> float:
    """Scene time (s) of a (sub-)frame, as Blender's Scene Time node: frame / (fps / fps_base)."""
    return float(frame) * scene.render.fps_base / scene.render.fps


def sensor_may_move(scene, sensor) -> bool:
    """True when the sensor's world matrix may change with time (animation, drivers, constraints, parents)."""
    from .export import animated

    obj = sensor
    while obj is not None:
        if animated(obj) or len(obj.constraints) or obj.rigid_body is not None:
            return True
        obj = obj.parent
    return animated(scene)


def _world_matrix_m(obj, scale_m: float) -> np.ndarray:
    m = np.array(obj.matrix_world, dtype=np.float64)
    m[:3, 3] *= scale_m
    return m


def motion_sample_count(duration_s: float, rate_hz: float, fps: float) -> int:
    """Poses sampled over a scan: ``rate_hz`` × duration, at most :data:`MOTION_SAMPLES_PER_FRAME` per Blender
    frame and :data:`MAX_MOTION_SAMPLES` in all, at least the two ends."""
    n = min(math.ceil(duration_s * rate_hz), math.ceil(duration_s * fps * MOTION_SAMPLES_PER_FRAME),
            MAX_MOTION_SAMPLES - 1)
    return max(1, n) + 1


def sample_trajectory(scene, sensor, frame: int, duration_s: float, rate_hz: float, scale_m: float = 1.0):
    """The sensor's pose over ``[0, duration_s]`` after the start of ``frame`` (sub-frames), or None when it does
    not move.  Leaves the scene at ``frame``."""
    if duration_s <= 0.0 or not sensor_may_move(scene, sensor):
        return None
    fps = scene.render.fps / scene.render.fps_base
    times = np.linspace(0.0, duration_s, motion_sample_count(duration_s, rate_hz, fps))
    matrices = []
    try:
        for t in times:
            f = frame + t * fps
            whole = math.floor(f)
            scene.frame_set(int(whole), subframe=float(f - whole))
            matrices.append(_world_matrix_m(sensor, scale_m))
    finally:
        scene.frame_set(frame)
    traj = Trajectory(times, np.array(matrices))
    return None if traj.is_static else traj


@dataclasses.dataclass
class FrameInputs:
    frame: int
    geometry: object            # core SceneGeometry (material overrides applied)
    world_from_sensor: np.ndarray
    trajectory: object | None   # core Trajectory (scanner with a moving sensor) or None
    start_time_s: float
    export: dict                # what the export did (counts, reused or not)


class FrameSource:
    """Each frame's inputs from Blender (main thread only), reusing the exported geometry while it is unchanged."""

    def __init__(self, scene, sensor, cfg, blender_materials, scale_m: float):
        self.scene, self.sensor, self.cfg = scene, sensor, cfg
        self.blender_materials = blender_materials
        self.scale_m = scale_m
        self.geometry, self.digest = None, None
        self.exports, self.geometries = 0, 0
        self.time_dependent = None   # {object: [reasons]} once known
        self.main_thread_s = 0.0     # time spent in prepare() (blocks the interface in a modal run)

    def _depsgraph(self):
        scene = self.scene
        view_layer = bpy.context.view_layer if bpy.context.scene == scene else scene.view_layers[0]
        depsgraph = view_layer.depsgraph
        depsgraph.update()
        return depsgraph

    def prepare(self, frame: int) -> FrameInputs:
        t0 = time.perf_counter()
        scene, sensor = self.scene, self.sensor
        scene.frame_set(frame)  # also at the current frame: evaluates the animation as a render would
        depsgraph = self._depsgraph()
        if self.time_dependent is None:
            self.time_dependent = frame_dependent_objects(scene, depsgraph, exclude={sensor.name})
        info = {"geometry": "reused"}
        if self.geometry is None or self.time_dependent:
            stats = {}
            exported = scene_geometry_from_depsgraph(depsgraph, unit_scale=self.scale_m, exclude={sensor.name},
                                                     stats=stats)
            self.exports += 1
            info.update(stats)
            if exported.n_triangles == 0:
                raise LadarError(f"no geometry to simulate at frame {frame}: the scene has no visible mesh (or "
                                 f"curve/text) objects enabled for rendering")
            _log(f"exported {stats['triangles']} triangles ({stats['objects']} objects, {stats['instances']} "
                 f"instances) at frame {frame}")
            overrides = {n: b for n, b in self.cfg.materials.items()
                         if n in exported.material_names or self.blender_materials.get(n) != b}
            geometry = exported.with_overrides(overrides)
            digest = geometry_digest(geometry)
            if digest != self.digest:
                self.geometry, self.digest = geometry, digest
                self.geometries += 1
                info["geometry"] = "exported"
        trajectory = None
        if self.cfg.system_type == "scanner":
            from ..core.config.derived import scan_duration_s
            trajectory = sample_trajectory(scene, sensor, frame, scan_duration_s(self.cfg),
                                           self.cfg.scanner.motion_samples_per_s, self.scale_m)
            info["motion_samples"] = 0 if trajectory is None else len(trajectory.times_s)
        inputs = FrameInputs(frame, self.geometry, _world_matrix_m(sensor, self.scale_m), trajectory,
                             scene_time_s(scene, frame), info)
        info["main_thread_s"] = time.perf_counter() - t0
        self.main_thread_s += info["main_thread_s"]
        return inputs


class _Request:
    """A worker's request for a frame's inputs, served by the main thread in :meth:`SimulationJob.step`."""

    def __init__(self, frame):
        self.frame, self.value, self.error = frame, None, None
        self.event = threading.Event()


# ------------------------------------------------------------------------------------------------------------
# The job
# ------------------------------------------------------------------------------------------------------------
class SimulationJob:
    """One simulation run (a frame or a frame sequence) from set-up to imported results.

    The constructor checks everything that can be checked without simulating (sensor, settings, run folder,
    result names, the first frame's geometry) and raises ConfigError/LadarError before anything is written.
    Then either :meth:`run` (blocking) or :meth:`start` ``(threaded=True)`` followed by :meth:`step` calls from
    the main thread until it returns True; :meth:`cancel` asks the core to stop (within one block of rays).

    States: "ready" → "running" → "done" | "failed" (``error``) | "cancelled".
    """

    def __init__(self, scene, *, frames=None, frame=None, out_dir=None, seed=None, config_path=None,
                 if_exists=None, overwrite=None, sensor=None, import_results=None, clouds=None, previews=None,
                 color_by=None, progress=None):
        props = scene.ladar
        self.scene = scene
        self.sensor = sensor if sensor is not None else active_sensor(scene)
        check_sensor(self.sensor)
        self.original_frame = scene.frame_current
        self.sequence = frames is not None
        if self.sequence:
            self.frames = [int(f) for f in frames]
            if not self.frames or len(set(self.frames)) != len(self.frames):
                raise ConfigError("frames", frames, "at least one frame, each frame once")
        else:
            if frame is not None and int(frame) != scene.frame_current:
                scene.frame_set(int(frame))
            self.frames = [scene.frame_current]
        if if_exists is None:
            if_exists = props.if_exists if overwrite is None else ("REPLACE" if overwrite else "STOP")
        if if_exists not in IF_EXISTS:
            raise ConfigError("if_exists", if_exists, "one of " + ", ".join(IF_EXISTS))
        self.if_exists = if_exists
        self.replace = if_exists == "REPLACE"
        self.import_results = props.import_results if import_results is None else bool(import_results)
        self.clouds = props.clouds if clouds is None else clouds
        if self.clouds not in CLOUDS:
            raise ConfigError("clouds", self.clouds, "one of " + ", ".join(CLOUDS))
        self.previews = props.write_previews if previews is None else bool(previews)
        self.color_by = props.color_by if color_by is None else color_by
        self.point_radius = props.point_radius
        self.config_path = config_path
        self.user_progress = progress

        last = self.frames[-1] if self.sequence else None
        run_path = resolve_run_dir(scene, self.sensor, self.frames[0], out_dir, last)
        self.requested_path = run_path  # "NEW": numbered from this name when the run claims its folder
        if if_exists == "NEW":
            run_path = free_run_path(run_path, self._name_taken)
        check_run_dir(run_path, overwrite=self.replace)  # replaces only a previous run (core.fileio.staging)
        self.run_path = run_path
        self.run_name = run_path.name
        if self.import_results:
            check_result_names(self.run_name, self.replace, self.frames if self.sequence else None, self.clouds)

        self.cfg, blender_materials = build_config(scene, self.sensor, config_path=config_path, seed=seed)
        self.scale_m = unit_scale(scene)
        self.source = FrameSource(scene, self.sensor, self.cfg, blender_materials, self.scale_m)
        self._inputs = {}
        first = self.source.prepare(self.frames[0])  # fails early on a scene without geometry
        self._inputs[first.frame] = first
        self.core_cfg = dataclasses.replace(self.cfg, materials={})  # overrides are applied to the geometry
        self.extra = self._extra_metadata(first)

        self.state = "ready"
        self.error = None
        self.result = None          # FrameResult of a one-frame run
        self.frame_stats = []       # per-frame stats of a sequence
        self.objects, self.images = [], []
        self.fraction, self.text = 0.0, "starting"
        self.threaded = False
        self.t_start = self.t_end = None
        self.max_step_s = 0.0       # longest main-thread step of a threaded run
        self._cancel = threading.Event()
        self._cancel_time = None
        self._lock = threading.Lock()
        self._request = None
        self._thread = None
        self._worker_done = threading.Event()
        self._worker_error = None
        self.claim = None           # core.fileio.staging.RunClaim from start() on

    # -- set-up helpers ---------------------------------------------------------------------------------------
    def _name_taken(self, path: Path) -> bool:
        """A run name whose results are already in the scene (with "NEW", the next name is taken)."""
        return self.import_results and bool(existing_results(path.name, self.frames if self.sequence else None,
                                                             self.clouds))

    def _extra_metadata(self, first: FrameInputs) -> dict:
        blender = {"version": bpy.app.version_string, "file": bpy.data.filepath, "scene": self.scene.name,
                   "sensor": self.sensor.name, "unit_scale_m": self.scale_m, "addon_version": core_version,
                   "config_file": None if self.config_path is None else str(self.config_path),
                   "time_dependent_objects": self.source.time_dependent}
        if not self.sequence:
            blender.update({"frame": first.frame, "export": first.export,
                            "export_s": first.export.get("main_thread_s")})
        # the core gets the material table applied to the geometry (so one BVH serves every frame); the recorded
        # settings are the full ones
        return {"blender": blender, "settings": config_to_dict(self.cfg)}

    # -- state --------------------------------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        return self.state in ("done", "failed", "cancelled")

    def cancel(self) -> None:
        """Ask the run to stop: the core raises Cancelled at its next block; nothing is written or imported."""
        if not self._cancel.is_set():
            self._cancel_time = time.perf_counter()
            self._cancel.set()

    def cancelled_requested(self) -> bool:
        return self._cancel.is_set()

    def _on_progress(self, fraction, text=""):
        self.fraction = float(fraction)
        self.text = str(text)
        if self.user_progress is not None:
            self.user_progress(fraction, text)

    # -- running ------------------------------------------------------------------------------------------------
    def start(self, threaded: bool = True) -> None:
        if self.state != "ready":
            raise RuntimeError(f"the job is {self.state}")
        # claim the folder's name now: a concurrent run of the same name refuses ("NEW": takes the next name)
        if self.if_exists == "NEW":
            self.claim = claim_run_dir(self.requested_path, if_exists="new", taken=self._name_taken)
        else:
            self.claim = claim_run_dir(self.run_path, if_exists=self.if_exists)
        self.run_path, self.run_name = self.claim.path, self.claim.path.name
        self.threaded = threaded
        self.state = "running"
        self.t_start = time.perf_counter()
        try:
            _log(f"simulating {self.run_name} ({self.cfg.system_type}, "
                 + (f"frames {self.frames[0]}…{self.frames[-1]} ({len(self.frames)})" if self.sequence
                    else f"frame {self.frames[0]}") + f", seed {self.cfg.run.seed}) into {self.run_path}")
            if threaded:
                self._thread = threading.Thread(target=self._worker_main, name="ladar-simulate", daemon=True)
                self._thread.start()
        except BaseException:
            self.claim.release()
            raise
        if not threaded:
            self._worker_main()
            self._finish()

    def run(self):
        """Run to the end in the calling thread.  Raises the run's error (Cancelled if cancelled)."""
        try:
            self.start(threaded=False)
        except BaseException:
            self.cancel()
            raise
        if self.state == "failed":
            raise self.error
        if self.state == "cancelled":
            raise Cancelled()
        return self

    def step(self) -> bool:
        """One main-thread step of a threaded run: serve the worker's request for a frame's inputs, and when the
        worker is done, import the results.  Returns True when the job has finished."""
        if self.finished:
            return True
        t0 = time.perf_counter()
        self._serve_request()
        if self._worker_done.is_set():
            self._thread.join()
            self._finish()
        self.max_step_s = max(self.max_step_s, time.perf_counter() - t0)
        return self.finished

    def wait(self, timeout_s: float | None = None, poll_s: float = 0.02) -> bool:
        """Call :meth:`step` until the job finishes (tests and scripts); returns :attr:`finished`."""
        t_end = None if timeout_s is None else time.perf_counter() + timeout_s
        while not self.step():
            if t_end is not None and time.perf_counter() > t_end:
                break
            time.sleep(poll_s)
        return self.finished

    def _serve_request(self):
        with self._lock:
            req, self._request = self._request, None
        if req is None:
            return
        try:
            req.value = self.source.prepare(req.frame)
        except BaseException as exc:  # handed to the worker, which fails the run with it
            req.error = exc
        finally:
            req.event.set()

    def _frame_inputs(self, frame: int) -> FrameInputs:
        """A frame's inputs, from the worker: prepared by the main thread (or inline when not threaded)."""
        inputs = self._inputs.get(frame)
        if inputs is not None:
            return inputs
        if not self.threaded:
            inputs = self.source.prepare(frame)
        else:
            req = _Request(frame)
            with self._lock:
                self._request = req
            while not req.event.wait(0.05):
                if self._cancel.is_set():
                    raise Cancelled()
            if req.error is not None:
                raise req.error
            inputs = req.value
        self._inputs = {frame: inputs}  # keep one frame: the callbacks of run_sequence ask several times
        return inputs

    def _worker_main(self):
        try:
            work = self.claim.work
            if self.sequence:
                self._work_sequence(work)
            else:
                self._work_frame(work)
            if self._cancel.is_set():
                raise Cancelled()
            self.claim.commit()
        except BaseException as exc:
            self._worker_error = exc
        finally:
            try:
                self.claim.release()  # the staging folder (and the folders the claim created, if not committed)
            finally:
                self._worker_done.set()

    def _work_frame(self, work: Path):
        inputs = self._frame_inputs(self.frames[0])
        _, self.result = run_simulation(inputs.geometry, inputs.world_from_sensor, self.core_cfg, work,
                                        frame=inputs.frame, overwrite=False, extra_metadata=self.extra,
                                        progress=self._on_progress, cancel=self._cancel.is_set,
                                        trajectory=inputs.trajectory, start_time_s=inputs.start_time_s)
        self._write_previews([work])

    def _work_sequence(self, work: Path):
        from ..core.sequence import run_sequence

        _, self.frame_stats = run_sequence(
            self.frames, lambda f: self._frame_inputs(f).geometry,
            lambda f: self._frame_inputs(f).world_from_sensor, self.core_cfg, work, overwrite=False,
            trajectory_for_frame=lambda f: self._frame_inputs(f).trajectory,
            start_time_for_frame=lambda f: self._frame_inputs(f).start_time_s,
            extra_metadata=self.extra, progress=self._on_progress, cancel=self._cancel.is_set)
        self._write_previews([work / f"frame_{f:04d}" for f in self.frames])
        link_image_sequences(work, self.frames)
        meta_path = work / "metadata.json"
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        meta["blender"]["geometry_exports"] = self.source.exports
        meta["blender"]["distinct_geometries"] = self.source.geometries
        meta.setdefault("files", {})["images/"] = ("each frame's images (hard links), numbered by scene frame: "
                                                   "one image sequence per product")
        meta_path.write_text(json.dumps(meta, indent=2), encoding="utf-8")

    def _write_previews(self, folders):
        if not self.previews:
            return
        from ..core.fileio.preview import write_run_previews
        for folder in folders:
            if self._cancel.is_set():
                raise Cancelled()
            self._on_progress(self.fraction, "PNG previews" + (f" {folder.name}" if self.sequence else ""))
            write_run_previews(folder, cancel=self._cancel.is_set)

    def _finish(self):
        """Main thread, after the worker: import the results, restore the frame, set the final state."""
        exc = self._worker_error
        if self.sequence and self.scene.frame_current != self.original_frame:
            try:
                self.scene.frame_set(self.original_frame)
            except ReferenceError:  # pragma: no cover - the scene was deleted meanwhile
                pass
        self.t_end = time.perf_counter()
        if isinstance(exc, Cancelled):
            self.state = "cancelled"
            self.text = "cancelled"
            _log(f"cancelled {self.run_name}: nothing written")
            return
        if exc is not None:
            self.state, self.error = "failed", exc
            self.text = f"failed: {exc}"
            return
        _log(f"wrote {self.run_path}")
        if self.import_results:
            try:
                self.objects, self.images = import_run(
                    self.run_path, self.scene, run_name=self.run_name, unit_scale=self.scale_m,
                    replace=self.replace, point_radius=self.point_radius, color_by=self.color_by,
                    clouds=self.clouds)
            except (LadarError, OSError, RuntimeError) as err:
                self.state = "failed"
                self.error = LadarError(f"the run was written to {self.run_path} but its import failed: {err}")
                return
        try:
            self.scene.ladar.last_run = str(self.run_path)
        except (AttributeError, ReferenceError):  # pragma: no cover
            pass
        self.fraction, self.text = 1.0, "done"
        self.state = "done"

    # -- reporting ------------------------------------------------------------------------------------------------
    def summary(self) -> str:
        if self.state == "done":
            if self.sequence:
                n = sum(s.get("n_points", 0) for s in self.frame_stats)
                return f"{n} points in {len(self.frames)} frames in {self.run_path}"
            return f"{len(self.result.points['range_m'])} points in {self.run_path}"
        if self.state == "failed":
            return str(self.error) or type(self.error).__name__
        return self.state

    def status_text(self) -> str:
        """One line for the status bar."""
        if self._cancel.is_set() and not self.finished:
            return f"Ladar {self.run_name}: cancelling…"
        return f"Ladar {self.run_name}: {100 * self.fraction:.0f}% {self.text}"


# ------------------------------------------------------------------------------------------------------------
# The interface's running job (one at a time) and the modal operator's event handling
# ------------------------------------------------------------------------------------------------------------
_current = {"job": None}


def current_job():
    """The job the modal operator is running, or None."""
    job = _current["job"]
    return job if job is not None and not job.finished else None


def set_current_job(job) -> None:
    _current["job"] = job


def handle_modal_event(job: SimulationJob, event_type: str, event_value: str = "NOTHING") -> str:
    """What the modal operator does with an event: ESC asks the job to cancel (and is consumed), a TIMER event
    advances it; returns the operator status: "RUNNING_MODAL", "PASS_THROUGH" (every other event: the
    interface stays usable), "FINISHED" (results imported) or "CANCELLED" (cancelled or failed: see
    ``job.state``)."""
    if event_type == "ESC" and event_value == "PRESS":
        job.cancel()
        return "RUNNING_MODAL"
    if event_type == "TIMER" and job.step():
        return "FINISHED" if job.state == "done" else "CANCELLED"
    return "PASS_THROUGH"


def link_image_sequences(seq_dir: Path, frames) -> list[Path]:
    """``images/<product>_<frame:04d>.exr`` (and ``.png``) hard links to each frame's images (copies where the
    file system has no hard links), so each product loads as one Blender image sequence numbered by frame."""
    out = []
    images = seq_dir / "images"
    for f in frames:
        for product in ("range", "intensity", "energy"):
            for ext in (".exr", ".png"):
                src = seq_dir / f"frame_{f:04d}" / f"{product}{ext}"
                if not src.is_file():
                    continue
                images.mkdir(exist_ok=True)
                dst = images / f"{product}_{f:04d}{ext}"
                try:
                    os.link(src, dst)
                except OSError:
                    shutil.copy2(src, dst)
                out.append(dst)
    return out


# ------------------------------------------------------------------------------------------------------------
# Script entry points (blocking)
# ------------------------------------------------------------------------------------------------------------
def simulate_scene(scene, out_dir=None, frame=None, seed=None, config_path=None, overwrite=None, *,
                   sensor=None, import_results=None, progress=None, if_exists=None, previews=None, color_by=None):
    """Simulate one frame of the scene's ladar sensor and (optionally) import the results.

    ``out_dir``: the run folder (default: ``<Scene.ladar.output_dir>/<sensor>_f<frame:04d>``); ``frame``: scene
    frame (default: the current one; the scene is left at it); ``seed``: run seed (default: ``Scene.ladar.seed``
    or the config file's); ``config_path``: a JSON/TOML config whose settings override the .blend's;
    ``overwrite``: True = ``if_exists`` "REPLACE", False = "STOP" (default: ``Scene.ladar.if_exists``);
    ``sensor``: a camera object (default: :func:`active_sensor`).

    Returns ``(run_path, FrameResult)``.  Raises ConfigError (bad settings) or LadarError (bad scene set-up)
    before anything is written.
    """
    if progress is None and bpy.app.background:
        progress = progress_printer()
    job = SimulationJob(scene, frame=frame, out_dir=out_dir, seed=seed, config_path=config_path,
                        overwrite=overwrite, if_exists=if_exists, sensor=sensor, import_results=import_results,
                        previews=previews, color_by=color_by, progress=progress).run()
    return job.run_path, job.result


def simulate_sequence(scene, frames, out_dir=None, seed=None, config_path=None, overwrite=None, *, sensor=None,
                      import_results=None, progress=None, if_exists=None, previews=None, clouds=None,
                      color_by=None):
    """Simulate the frames ``frames`` (e.g. :func:`parse_frames`) into one sequence run folder.

    Same options as :func:`simulate_scene`, plus ``clouds``: "RUN" (one merged point cloud) or "FRAME" (one per
    frame).  The scene returns to its current frame.  Returns ``(run_path, per-frame stats)``.
    """
    if progress is None and bpy.app.background:
        progress = progress_printer()
    job = SimulationJob(scene, frames=frames, out_dir=out_dir, seed=seed, config_path=config_path,
                        overwrite=overwrite, if_exists=if_exists, sensor=sensor, import_results=import_results,
                        previews=previews, clouds=clouds, color_by=color_by, progress=progress).run()
    return job.run_path, job.frame_stats

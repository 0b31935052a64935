"""One simulation run driven from Blender (:class:`SimulationJob`): the core runs in a worker thread (or inline),
the main thread serves it each frame's inputs and imports the results.  Also the interface's running job and the
modal operator's event handling."""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import threading
import time
from pathlib import Path

import bpy

from ..core.errors import ConfigError
from ..core.version import __version__ as core_version
from ..core.config.files import config_to_dict
from ..core.errors import Cancelled
from ..core.run import run_simulation
from ..core.fileio.staging import check_run_dir, claim_run_dir, free_run_path
from .background import BackgroundJob, current_job, handle_modal_event, set_current_job  # noqa: F401
from .errors import LadarError
from .blend_config import check_sensor, unit_scale
from .results import check_result_names, existing_results, import_run

from .frames import FrameInputs, FrameSource
from .run_inputs import active_sensor, build_config, log, resolve_run_dir

IF_EXISTS = ("STOP", "REPLACE", "NEW")
CLOUDS = ("RUN", "FRAME")

class _Request:
    """A worker's request for a frame's inputs, served by the main thread in :meth:`SimulationJob.step`."""

    def __init__(self, frame):
        self.frame, self.value, self.error = frame, None, None
        self.event = threading.Event()


# ------------------------------------------------------------------------------------------------------------
# The job
# ------------------------------------------------------------------------------------------------------------
class SimulationJob(BackgroundJob):
    """One simulation run (a frame or a frame sequence) from set-up to imported results.

    The constructor checks everything that can be checked without simulating (sensor, settings, run folder,
    result names, the first frame's geometry) and raises ConfigError/LadarError before anything is written.
    Then either :meth:`run` (blocking) or :meth:`start` ``(threaded=True)`` followed by :meth:`step` calls from
    the main thread until it returns True; :meth:`cancel` asks the core to stop (within one block of rays).

    States: "ready" → "running" → "done" | "failed" (``error``) | "cancelled".
    """

    POLL_S = 0.02

    def __init__(self, scene, *, frames=None, frame=None, out_dir=None, seed=None, config_path=None,
                 if_exists=None, overwrite=None, sensor=None, import_results=None, clouds=None, previews=None,
                 color_by=None, progress=None, preview_pool=None):
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
        self.preview_pool = preview_pool  # core.fileio.preview_worker.PreviewPool (a headless command's) or None
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
    def cancel(self) -> None:
        """Ask the run to stop: the core raises Cancelled at its next block; nothing is written or imported."""
        if not self._cancel.is_set():
            self._cancel_time = time.perf_counter()
            self._cancel.set()

    def cancelled_requested(self) -> bool:
        return self._cancel.is_set()

    def _on_progress(self, fraction, text="", part=None):
        """``part=(done, total)``: a step after the blocks (the previews), shown as ``text done/total``."""
        self.fraction = float(fraction)
        self.text = str(text) + (f" {part[0]}/{part[1]}" if part is not None else "")
        if self.user_progress is not None:
            if part is None:
                self.user_progress(fraction, text)
            else:
                self.user_progress(fraction, text, part=part)

    # -- running ------------------------------------------------------------------------------------------------
    def start(self, threaded: bool = True) -> None:
        if self.state != "ready":
            raise RuntimeError(f"the job is {self.state}")
        # claim the folder's name now: a concurrent run of the same name refuses ("NEW": takes the next name)
        if self.if_exists == "NEW":
            self.claim = claim_run_dir(self.requested_path, if_exists="new", taken=self._name_taken)
        else:
            self.claim = claim_run_dir(self.run_path, if_exists=self.if_exists)
        try:
            self.run_path, self.run_name = self.claim.path, self.claim.path.name
            self.threaded = threaded
            self.state = "running"
            self.t_start = time.perf_counter()
            log(f"simulating {self.run_name} ({self.cfg.system_type}, "
                 + (f"frames {self.frames[0]}…{self.frames[-1]} ({len(self.frames)})" if self.sequence
                    else f"frame {self.frames[0]}") + f", seed {self.cfg.run.seed}) into {self.run_path}")
            if threaded:
                self._thread = threading.Thread(target=self._worker_main, name="ladar-simulate", daemon=True)
                self._thread.start()
            else:
                self._worker_main()
        except BaseException:  # (a signal between the claim and the worker's own clean-up included)
            if self._thread is None or not self._thread.is_alive():  # (a started worker releases it itself)
                self.claim.release()
            raise
        if not threaded:
            self._finish()

    def run(self):
        """Run to the end in the calling thread.  Raises the run's error (Cancelled if cancelled)."""
        try:
            self.start(threaded=False)
        except BaseException:
            self.cancel()
            raise
        return self.raise_outcome()

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
        """The run's PNG previews: by the command's preview workers where it has them (core.fileio.preview_worker:
        drawn on the other core meanwhile loaded, byte for byte the same PNGs), else, and for the share of a
        worker that failed, here."""
        if not self.previews:
            return
        folders = list(folders)

        def what(folder):
            return "PNG previews" + (f" {folder.name}" if self.sequence else "")

        todo = [(folder, None) for folder in folders]
        pool = self.preview_pool
        if pool is not None:
            for message in pool.notes:
                log(f"note: {message}")
            pool.notes.clear()
        if pool is not None and pool.workers:  # (draw() says so if none is running any more)
            from ..core.fileio.preview import preview_count

            totals = [preview_count(folder) for folder in folders]
            self._on_progress(self.fraction, what(folders[0]), (0, totals[0]))
            todo = pool.draw(folders, cancel=self._cancel.is_set, note=lambda m: log(f"note: {m}"),
                             progress=lambda i, done: self._on_progress(self.fraction, what(folders[i]),
                                                                        (done, totals[i])))
        if not todo:
            return
        from ..core.fileio.preview import write_run_previews
        for folder, share in todo:
            if self._cancel.is_set():
                raise Cancelled()
            write_run_previews(folder, cancel=self._cancel.is_set, share=share,
                               progress=lambda done, total, w=what(folder): self._on_progress(self.fraction, w,
                                                                                             (done, total)))

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
            log(f"cancelled {self.run_name}: nothing written")
            return
        if exc is not None:
            self.state, self.error = "failed", exc
            self.text = f"failed: {exc}"
            return
        log(f"wrote {self.run_path}")
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
            from ..core.fileio.run_folder import combine_figures, run_figures

            fig = (combine_figures([s["figures"] for s in self.frame_stats]) if self.sequence
                   else run_figures(self.result))
            fa = fig.get("false_alarms")
            what = f"{fig['points']} points" + (f" ({fa} false alarms)" if fa is not None else "")
            return f"{what} in {len(self.frames)} frames in {self.run_path}" if self.sequence else \
                f"{what} in {self.run_path}"
        if self.state == "failed":
            return str(self.error) or type(self.error).__name__
        return self.state

    def warnings(self) -> list[str]:
        """What a finished run warns about (core.fileio.run_folder.run_warnings: the range gate's coverage), one
        line each; a sequence's per frame."""
        from ..core.fileio.run_folder import run_warnings

        if self.state != "done":
            return []
        if self.sequence:
            return [f"frame {f}: {w}" for f, st in zip(self.frames, self.frame_stats) for w in run_warnings(st)]
        return run_warnings(self.result.stats)

    def status_text(self) -> str:
        """One line for the status bar."""
        if self._cancel.is_set() and not self.finished:
            return f"Ladar {self.run_name}: cancelling…"
        return f"Ladar {self.run_name}: {100 * self.fraction:.0f}% {self.text}"


# ------------------------------------------------------------------------------------------------------------
# The interface's running job and the modal operator's event handling live in .background (imported above, the
# same objects under this module's names as before): the operators and the status bar use them without importing
# the simulator.
# ------------------------------------------------------------------------------------------------------------


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



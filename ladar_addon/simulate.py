"""Simulate the scene's ladar sensor: export → settings → core → run folder → results in Blender.

Usable from scripts::

    from bl_ext.<repo>.ladar_simulator.ladar_addon.simulate import simulate_scene, simulate_sequence
    from bl_ext.<repo>.ladar_simulator.ladar_addon.frames import parse_frames
    run_path, result = simulate_scene(bpy.context.scene, out_dir="/tmp/runs/r1", frame=1, seed=7)
    seq_path, frame_stats = simulate_sequence(bpy.context.scene, parse_frames("1-100"), out_dir="/tmp/runs/s1")

A run is a :class:`~ladar_addon.job.SimulationJob` (``job.py``; each frame's inputs: ``frames.py``; the
sensor, run folder name and settings a run starts from: ``run_inputs.py``).  Everything that reads Blender data happens on the main thread (export of the
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


import bpy

from .job import SimulationJob
from .moved import moved_names
from .run_inputs import progress_printer

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
    printer = progress_printer() if progress is None and bpy.app.background else None
    try:
        job = SimulationJob(scene, frame=frame, out_dir=out_dir, seed=seed, config_path=config_path,
                            overwrite=overwrite, if_exists=if_exists, sensor=sensor, import_results=import_results,
                            previews=previews, color_by=color_by, progress=printer or progress).run()
    finally:
        if printer is not None:
            printer.close()
    return job.run_path, job.result


def simulate_sequence(scene, frames, out_dir=None, seed=None, config_path=None, overwrite=None, *, sensor=None,
                      import_results=None, progress=None, if_exists=None, previews=None, clouds=None,
                      color_by=None):
    """Simulate the frames ``frames`` (e.g. :func:`parse_frames`) into one sequence run folder.

    Same options as :func:`simulate_scene`, plus ``clouds``: "RUN" (one merged point cloud) or "FRAME" (one per
    frame).  The scene returns to its current frame.  Returns ``(run_path, per-frame stats)``.
    """
    printer = progress_printer() if progress is None and bpy.app.background else None
    try:
        job = SimulationJob(scene, frames=frames, out_dir=out_dir, seed=seed, config_path=config_path,
                            overwrite=overwrite, if_exists=if_exists, sensor=sensor, import_results=import_results,
                            previews=previews, clouds=clouds, color_by=color_by, progress=printer or progress).run()
    finally:
        if printer is not None:
            printer.close()
    return job.run_path, job.frame_stats


#: Names that lived here before the job, the frames and the run inputs got their own modules.
_MOVED = {"job": ("current_job", "set_current_job", "handle_modal_event", "link_image_sequences",
                  "IF_EXISTS", "CLOUDS"),
          "frames": ("parse_frames", "scene_time_s", "sensor_may_move", "motion_sample_count", "sample_trajectory",
                     "FrameInputs", "FrameSource", "MAX_MOTION_SAMPLES", "MOTION_SAMPLES_PER_FRAME"),
          "run_inputs": ("active_sensor", "default_run_name", "resolve_run_dir", "build_config",
                         "print_error")}


__getattr__ = moved_names(__name__, _MOVED)

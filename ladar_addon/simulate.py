"""Simulate the active ladar sensor of a scene: export → settings → core pipeline → results in Blender.

Usable from scripts::

    from bl_ext.<repo>.ladar_simulator.ladar_addon.simulate import simulate_scene
    run_path, result = simulate_scene(bpy.context.scene, out_dir="/tmp/runs", frame=1, seed=7)

``out_dir`` is the run folder itself (as for ``core.pipeline.run_simulation``); by default it is
``<Scene.ladar.output_dir>/<sensor>_f<frame:04d>``.  The imported point cloud and images are named after it.
"""
from __future__ import annotations

import json
import re
import sys
import time
from pathlib import Path

import bpy
import numpy as np

from .. import core
from ..core.config import ConfigError, load_config, validate
from ..core.pipeline import run_simulation
from .errors import LadarError
from .export import scene_geometry_from_depsgraph
from .properties import check_sensor, config_from_blender, unit_scale
from .results import check_result_names, import_run
from .sensor import camera_receiver_fov_rad


def active_sensor(scene):
    """The scene's ladar sensor: ``Scene.ladar.sensor``, else the scene camera.  Raises LadarError."""
    sensor = scene.ladar.sensor or scene.camera
    if sensor is None:
        raise LadarError("no ladar sensor: set Scene > Ladar > Sensor or the scene camera to a camera object")
    check_sensor(sensor)
    return sensor


def default_run_name(sensor, frame: int) -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", sensor.name).strip("._") or "sensor"
    return f"{name}_f{frame:04d}"


def resolve_run_dir(scene, sensor, frame: int, out_dir=None) -> Path:
    """The absolute run folder: ``out_dir``, else ``<Scene.ladar.output_dir>/<sensor>_f<frame>``.

    A path starting with ``//`` is relative to the .blend file, which must then be saved.
    """
    if out_dir is not None:
        path = str(out_dir)
    else:
        if not scene.ladar.output_dir:
            raise LadarError("no output folder: set Scene > Ladar > Output Folder or pass --out")
        base = scene.ladar.output_dir
        path = base + ("" if base.endswith(("/", "\\")) else "/") + default_run_name(sensor, frame)
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
    ``receiver.fov_x_rad``/``fov_y_rad`` itself.
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


def _progress_printer():
    state = {"next": 0.0, "t0": time.perf_counter()}

    def progress(fraction, message=""):
        if fraction + 1e-9 >= state["next"] or fraction >= 1.0:
            print(f"ladar: {100 * fraction:5.1f}% {message} ({time.perf_counter() - state['t0']:.2f} s)",
                  flush=True)
            state["next"] = min(1.0, fraction + 0.1)
    return progress


def _log(message):
    if bpy.app.background:
        print(f"ladar: {message}", flush=True)


def simulate_scene(scene, out_dir=None, frame=None, seed=None, config_path=None, overwrite=None, *,
                   sensor=None, import_results=None, progress=None):
    """Simulate one frame of the scene's ladar sensor and (optionally) import the results.

    ``out_dir``: the run folder (default: ``<Scene.ladar.output_dir>/<sensor>_f<frame:04d>``); ``frame``: scene frame
    (default: the current one); ``seed``: run seed (default: ``Scene.ladar.seed`` or the config file's);
    ``config_path``: a JSON/TOML config whose settings override the .blend's; ``overwrite``: replace an existing
    run folder and result objects (default: ``Scene.ladar.overwrite``); ``sensor``: a camera object (default:
    :func:`active_sensor`).

    Returns ``(run_path, FrameResult)``.  Raises ConfigError (bad settings) or LadarError (bad scene set-up)
    before anything is written.
    """
    if sensor is None:
        sensor = active_sensor(scene)
    else:
        check_sensor(sensor)
    if frame is not None and int(frame) != scene.frame_current:
        scene.frame_set(int(frame))
    frame = scene.frame_current
    overwrite = scene.ladar.overwrite if overwrite is None else bool(overwrite)
    import_results = scene.ladar.import_results if import_results is None else bool(import_results)
    run_path = resolve_run_dir(scene, sensor, frame, out_dir)
    run_name = run_path.name
    if run_path.exists() and not overwrite:
        raise ConfigError("out", str(run_path), "a run folder that does not exist yet (or overwrite it: "
                                                "--overwrite, Scene > Ladar > Overwrite)")

    cfg, blender_materials = build_config(scene, sensor, config_path=config_path, seed=seed)
    if import_results:
        check_result_names(run_name, overwrite)

    t0 = time.perf_counter()
    view_layer = bpy.context.view_layer if bpy.context.scene == scene else scene.view_layers[0]
    depsgraph = view_layer.depsgraph
    depsgraph.update()
    scale = unit_scale(scene)
    stats = {}
    geometry = scene_geometry_from_depsgraph(depsgraph, unit_scale=scale, exclude={sensor.name}, stats=stats)
    if geometry.n_triangles == 0:
        raise LadarError("no geometry to simulate: the scene has no visible mesh (or curve/text) objects "
                         "enabled for rendering")
    export_s = time.perf_counter() - t0
    _log(f"exported {stats['triangles']} triangles ({stats['objects']} objects, {stats['instances']} instances) "
         f"in {export_s:.3f} s")
    # Materials the .blend lists but the visible geometry does not use are not overrides; a config file's
    # unknown material names still raise (core SceneGeometry.with_overrides).
    cfg.materials = {name: brdf for name, brdf in cfg.materials.items()
                     if name in geometry.material_names or blender_materials.get(name) != brdf}

    world_from_sensor = np.array(sensor.matrix_world, dtype=np.float64)
    world_from_sensor[:3, 3] *= scale
    extra = {"blender": {"version": bpy.app.version_string, "file": bpy.data.filepath, "scene": scene.name,
                         "sensor": sensor.name, "frame": frame, "unit_scale_m": scale, "export_s": export_s,
                         "export": stats, "config_file": None if config_path is None else str(config_path),
                         "addon_version": core.__version__}}
    if progress is None and bpy.app.background:
        progress = _progress_printer()
    _log(f"simulating {run_name} (frame {frame}, seed {cfg.run.seed}) into {run_path}")
    path, result = run_simulation(geometry, world_from_sensor, cfg, run_path, frame=frame, overwrite=overwrite,
                                  extra_metadata=extra, progress=progress)
    _log(f"wrote {path} ({len(result.points['range_m'])} points)")
    if import_results:
        import_run(path, result, scene, run_name=run_name, unit_scale=scale, overwrite=overwrite,
                   point_radius=scene.ladar.point_radius)
    return path, result


def print_error(message: str) -> None:
    print(f"ladar: error: {message}", file=sys.stderr, flush=True)

"""What a run starts from: the active sensor, the run folder's name, the settings (scene, config file, seed), and
the messages a run prints."""
from __future__ import annotations

import math
import os
import re
import threading
import time
from pathlib import Path

import bpy

from ..core.config.validate import validate
from ..core.config.files import config_from_dict, read_config_file
from ..core.config.preset_files import resolve_preset
from ..core.fileio.staging import refuse_symlink
from ..core.process import emit
from .errors import LadarError
from .blend_config import check_sensor, config_from_blender
from .sensor import camera_receiver_fov_rad


# ------------------------------------------------------------------------------------------------------------
# Names, folders, settings
# ------------------------------------------------------------------------------------------------------------
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
    path = Path(path).expanduser()
    refuse_symlink(Path(os.path.abspath(path)))  # (before resolve(), which would follow it)
    return path.resolve()


def build_config(scene, sensor, *, config_path=None, seed=None):
    """The run's settings: the .blend's, then the config file's, then ``seed``.  Validated.

    The receiver field of view follows the camera for the final receiver size, unless the config file sets
    ``receiver.fov_x_rad``/``fov_y_rad`` itself.  Returns (config, the .blend's material table).
    """
    cfg = config_from_blender(scene, sensor)
    blender_materials = dict(cfg.materials)
    if config_path is not None:
        data = read_config_file(config_path)
        cfg = config_from_dict(data, base=cfg)
        receiver = resolve_preset(data).get("receiver", {})  # the settings the file (or its preset) sets itself
        if not isinstance(receiver, dict) or not ({"fov_x_rad", "fov_y_rad"} & set(receiver)):
            rx = cfg.receiver
            rx.fov_x_rad, rx.fov_y_rad = camera_receiver_fov_rad(sensor.data, rx.width_px, rx.height_px)
    if seed is not None:
        cfg.run.seed = int(seed)
    validate(cfg)
    return cfg, blender_materials


def progress_printer(prefix="ladar: ", every_s=None):
    """A progress callback that prints a line at most every 10 % (background mode: Blender draws nothing), and
    also when ``every_s`` seconds passed since the last line (long sweeps)."""
    state = {"next": 0.0, "t0": time.perf_counter(), "last": -math.inf, "lock": threading.Lock()}

    def progress(fraction, message=""):
        with state["lock"]:
            now = time.perf_counter()
            if (fraction + 1e-9 >= state["next"] or fraction >= 1.0
                    or (every_s is not None and now - state["last"] >= every_s)):
                emit(f"{prefix}{100 * fraction:5.1f}% {message} ({now - state['t0']:.2f} s)")
                state["next"] = min(1.0, max(state["next"], fraction + 0.1))
                state["last"] = now
    return progress


def log(message):
    if bpy.app.background:
        emit(f"ladar: {message}")


def print_error(message: str) -> None:
    emit(f"ladar: error: {message}", err=True)



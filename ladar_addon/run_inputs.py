"""What a run starts from: the active sensor, the run folder's name, the settings (scene, config file, seed), and
the messages a run prints."""
from __future__ import annotations

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


#: Longest silence (s) of a progress printer: its heartbeat repeats the last line, with the time so far and an
#: estimate of the time left, when nothing was printed for this long (a run never goes quiet for more than 2 s).
HEARTBEAT_S = 1.0


def format_eta(elapsed_s: float, fraction: float) -> str:
    """The estimated time left of a run ``fraction`` done after ``elapsed_s`` (linear in the fraction):
    "ETA 12 s", "ETA 3 min 20 s"; "ETA unknown" before 1 % and "finishing" once the fraction is 1."""
    if fraction >= 1.0:
        return "finishing"
    if fraction < 0.01 or elapsed_s <= 0.0:
        return "ETA unknown"
    left = elapsed_s * (1.0 - fraction) / fraction
    if left < 60.0:
        return f"ETA {left:.0f} s"
    if left < 3600.0:
        return f"ETA {int(left // 60)} min {int(left % 60):02d} s"
    return f"ETA {int(left // 3600)} h {int(left % 3600 // 60):02d} min"


class ProgressPrinter:
    """A progress callback ``(fraction, message)`` that prints a line at most every 10 % (background mode:
    Blender draws nothing), also when ``every_s`` seconds passed since the last line (long sweeps), each with the
    time so far and the estimated time left; and a heartbeat thread that repeats the last line whenever nothing
    was printed for ``heartbeat_s`` (building the BVH, writing previews, a long block: never silent for more than
    2 s).  The heartbeat starts with the printer; :meth:`close` (or leaving a ``with`` block) stops it.

    A step after the frame's blocks (fraction 1: the PNG previews) passes ``part=(done, total)``: its lines say
    ``done/total`` and their ETA is the step's own, from the time since its ``done = 0`` (a line at most every
    10 % of the step, the heartbeat between).

    The ETA counts from the first progress past 0 on (the end of the first block): the time before it includes
    loading or compiling the kernels, once per run, which the blocks after it do not repeat (counted from the
    start, a 9 s compile and 1 s blocks of 10 % each gave "ETA 44 s" at 20 % instead of 8 s).  The first such
    line itself has only the time from the start."""

    def __init__(self, prefix="ladar: ", every_s=None, heartbeat_s=HEARTBEAT_S, eta=True):
        self.prefix, self.every_s, self.heartbeat_s, self.eta = prefix, every_s, heartbeat_s, eta
        self._lock = threading.Lock()
        self._t0 = time.perf_counter()
        self._next, self._last = 0.0, time.perf_counter()
        self._fraction, self._message = 0.0, "starting"
        self._part = None  # (done, total, the step's start time, its next 10 % to print)
        self._anchor = None  # (time, fraction) of the first progress past 0: the ETA's origin from then on
        self._stop = threading.Event()
        self._thread = None
        if heartbeat_s:
            self._thread = threading.Thread(target=self._beat, name="ladar progress heartbeat", daemon=True)
            self._thread.start()

    def _line(self, now) -> str:
        elapsed = now - self._t0
        if self._part is not None:
            done, total, t_part, _ = self._part
            eta = format_eta(now - t_part, done / total if total else 1.0)
            return f"{self.prefix}{100 * self._fraction:5.1f}% {self._message} {done}/{total} ({elapsed:.2f} s, {eta})"
        if not self.eta:  # (the messages carry their own: the sweep's, from its tasks' times)
            return f"{self.prefix}{100 * self._fraction:5.1f}% {self._message} ({elapsed:.2f} s)"
        return (f"{self.prefix}{100 * self._fraction:5.1f}% {self._message} "
                f"({elapsed:.2f} s, {self._eta(now, elapsed)})")

    def _eta(self, now, elapsed) -> str:
        f = self._fraction
        if self._anchor is None or f >= 1.0 or f <= self._anchor[1]:
            return format_eta(elapsed, f)
        t_a, f_a = self._anchor
        # the rate of the blocks after the first: (f - f_a) done in (now - t_a), scaled to the fraction's scale
        return format_eta((now - t_a) * f / (f - f_a), f)

    def __call__(self, fraction, message="", part=None):
        with self._lock:
            now = time.perf_counter()
            self._fraction, self._message = float(fraction), str(message)
            if part is not None:
                done, total = int(part[0]), int(part[1])
                if self._part is None or done == 0:
                    self._part = (done, total, now, 0.0)
                f = done / total if total else 1.0
                self._part = (done, total, self._part[2], self._part[3])
                if f + 1e-9 >= self._part[3]:
                    emit(self._line(now))
                    self._part = (done, total, self._part[2], min(1.0, f + 0.1) if f < 1.0 else 2.0)
                    self._last = now
                return
            self._part = None
            if self._anchor is None and 0.0 < self._fraction < 1.0:
                self._anchor = (now, self._fraction)
            if (fraction + 1e-9 >= self._next or fraction >= 1.0
                    or (self.every_s is not None and now - self._last >= self.every_s)):
                emit(self._line(now))
                self._next = min(1.0, max(self._next, fraction + 0.1))
                self._last = now

    def set(self, fraction, message="") -> None:
        """The state the heartbeat repeats (nothing printed now): ``fraction`` done, ``message`` what runs."""
        with self._lock:
            self._fraction, self._message = float(fraction), str(message)

    def say(self, text: str) -> None:
        """Print ``text`` as it is (a line of its own, e.g. a finished step); the heartbeat waits
        ``heartbeat_s`` from now."""
        with self._lock:
            emit(text)
            self._last = time.perf_counter()

    def _beat(self):
        while not self._stop.wait(min(0.25, self.heartbeat_s)):
            with self._lock:
                now = time.perf_counter()
                if now - self._last >= self.heartbeat_s:
                    emit(self._line(now))
                    self._last = now

    def close(self):
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def progress_printer(prefix="ladar: ", every_s=None, heartbeat_s=HEARTBEAT_S, eta=True) -> ProgressPrinter:
    """A :class:`ProgressPrinter` (close it when the run is over: it has a heartbeat thread); ``eta=False`` when
    the messages carry their own ETA."""
    return ProgressPrinter(prefix, every_s, heartbeat_s, eta)


def log(message):
    if bpy.app.background:
        emit(f"ladar: {message}")


def print_error(message: str) -> None:
    emit(f"ladar: error: {message}", err=True)



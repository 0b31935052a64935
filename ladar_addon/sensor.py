"""The receiver's field of view from the Blender camera (the sensor object).

The receiver has ``width_px`` × ``height_px`` square pixels.  The camera's angle applies to the sensor dimension
chosen by its *sensor fit*, exactly as Blender applies it to a render of ``width_px`` × ``height_px`` pixels:

* ``HORIZONTAL``: the camera angle is the horizontal field of view; fov_y = 2·atan(tan(fov_x/2)·H/W);
* ``VERTICAL``: the camera angle is the vertical field of view;     fov_x = 2·atan(tan(fov_y/2)·W/H);
* ``AUTO``: the angle applies to the larger of the two dimensions (horizontal when W ≥ H).

The camera angle along the fitted dimension is 2·atan(sensor_size / (2·lens)), with ``sensor_width`` for the
``AUTO`` and ``HORIZONTAL`` fits and ``sensor_height`` for ``VERTICAL`` (Blender's ``Camera.angle``).
Lens shift, orthographic and panoramic cameras are not supported.
"""
from __future__ import annotations

import math

from ..core.errors import ConfigError


def receiver_fov_rad(sensor_fit: str, fit_angle_rad: float, width_px: int, height_px: int) -> tuple[float, float]:
    """Full horizontal and vertical field of view (rad) of a ``width_px`` × ``height_px`` square-pixel receiver
    whose camera has angle ``fit_angle_rad`` along the dimension chosen by ``sensor_fit``."""
    if width_px <= 0 or height_px <= 0:
        raise ConfigError("receiver.width_px" if width_px <= 0 else "receiver.height_px",
                          width_px if width_px <= 0 else height_px, "a whole number ≥ 1")
    fit = _resolve_fit(sensor_fit, width_px, height_px)
    half_tan = math.tan(0.5 * fit_angle_rad)
    if fit == "HORIZONTAL":
        half_x, half_y = half_tan, half_tan * height_px / width_px
    else:
        half_x, half_y = half_tan * width_px / height_px, half_tan
    return 2.0 * math.atan(half_x), 2.0 * math.atan(half_y)


def _resolve_fit(sensor_fit: str, width_px: int, height_px: int) -> str:
    if sensor_fit == "AUTO":
        return "HORIZONTAL" if width_px >= height_px else "VERTICAL"
    if sensor_fit not in ("HORIZONTAL", "VERTICAL"):
        raise ValueError(f"unknown sensor fit {sensor_fit!r}")
    return sensor_fit


def camera_fit_angle_rad(camera) -> float:
    """The angle of a ``bpy.types.Camera`` along the sensor dimension its sensor fit uses."""
    size = camera.sensor_height if camera.sensor_fit == "VERTICAL" else camera.sensor_width
    return 2.0 * math.atan(0.5 * size / camera.lens)


def check_camera(camera, name: str = "sensor") -> None:
    """Raise ConfigError unless ``camera`` is a perspective camera without lens shift."""
    if camera.type != "PERSP":
        raise ConfigError(f"{name}.type", camera.type, "a perspective camera ('PERSP')")
    if camera.shift_x != 0.0 or camera.shift_y != 0.0:
        raise ConfigError(f"{name}.shift", (camera.shift_x, camera.shift_y), "no lens shift (0, 0)")


def camera_receiver_fov_rad(camera, width_px: int, height_px: int) -> tuple[float, float]:
    """(fov_x, fov_y) in radians of a receiver of ``width_px`` × ``height_px`` behind ``camera``."""
    check_camera(camera)
    return receiver_fov_rad(camera.sensor_fit, camera_fit_angle_rad(camera), width_px, height_px)


def set_camera_receiver_fov(camera, fov_x_rad: float, fov_y_rad: float, width_px: int, height_px: int,
                            rel_tol: float = 1e-5) -> None:
    """Set the camera angle so that :func:`camera_receiver_fov_rad` gives (fov_x, fov_y).

    Pixels are square, so fov_y follows from fov_x and the pixel counts; a pair that disagrees by more than
    ``rel_tol`` (in tan(fov/2)) raises ConfigError naming ``receiver.fov_y_rad``.
    """
    check_camera(camera)
    want_y = 2.0 * math.atan(math.tan(0.5 * fov_x_rad) * height_px / width_px)
    if abs(math.tan(0.5 * want_y) - math.tan(0.5 * fov_y_rad)) > rel_tol * math.tan(0.5 * want_y):
        raise ConfigError("receiver.fov_y_rad", fov_y_rad,
                          f"{want_y!r} rad: square pixels give fov_y = 2·atan(tan(fov_x/2)·H/W) for "
                          f"fov_x = {fov_x_rad!r} rad and {width_px}×{height_px} px")
    fit = _resolve_fit(camera.sensor_fit, width_px, height_px)
    size = camera.sensor_height if camera.sensor_fit == "VERTICAL" else camera.sensor_width
    angle = fov_x_rad if fit == "HORIZONTAL" else fov_y_rad
    camera.lens = 0.5 * size / math.tan(0.5 * angle)


# ------------------------------------------------------------------------------------------------------------
# What each sensor system type uses (paper §2): the panels show only these settings
# ------------------------------------------------------------------------------------------------------------
#: Sensor settings groups each system type reads.  A group the core adds later and that is listed nowhere here
#: is shown for every system type.
SYSTEM_GROUPS = {
    "flash": ("laser", "receiver", "gate", "detection", "detector", "run"),
    "profiler": ("laser", "receiver", "gate", "detection", "detector", "run"),
    "scanner": ("laser", "receiver", "gate", "scanner", "detection", "detector", "run"),
    "gated": ("laser", "receiver", "gated", "detector", "run"),
}
#: Settings a system type ignores inside a group it uses: (group, name).
SYSTEM_HIDDEN_FIELDS = {
    "flash": frozenset(),
    "profiler": frozenset({("receiver", "width_px"), ("receiver", "height_px")}),  # one detector element
    "scanner": frozenset({("receiver", "width_px"), ("receiver", "height_px"), ("receiver", "subsamples"),
                          ("laser", "divergence_fills_fov")}),  # a steered beam: no receiver array, no FOV fill
    "gated": frozenset(),
}
#: Scanner settings that apply to some scan patterns only.
SCAN_PATTERN_FIELDS = {"n_lines": ("raster",), "n_channels": ("rotating",), "cone_half_angle_rad": ("palmer",),
                       "cone_half_angle_y_rad": ("palmer",),
                       "scan_width_rad": ("raster", "oscillating", "rotating"),
                       "scan_height_rad": ("raster", "rotating")}


def group_used(system_type: str, group: str) -> bool:
    """Does a sensor of ``system_type`` read the settings group ``group``?"""
    listed = set().union(*SYSTEM_GROUPS.values())
    return group not in listed or group in SYSTEM_GROUPS.get(system_type, ())


def field_used(system_type: str, group: str, name: str, scan_pattern: str | None = None) -> bool:
    """Does a sensor of ``system_type`` read the setting ``group.name``?  (Scanner settings also depend on the
    scan pattern.)"""
    if not group_used(system_type, group) or (group, name) in SYSTEM_HIDDEN_FIELDS.get(system_type, ()):
        return False
    if group == "scanner" and scan_pattern is not None and name in SCAN_PATTERN_FIELDS:
        return scan_pattern in SCAN_PATTERN_FIELDS[name]
    return True

"""How result point clouds are coloured: the attribute chosen (``Scene.ladar.color_by``), its scale and the
colour ramp, applied to every result object of a scene; the points' display radius."""
from __future__ import annotations


import bpy
import numpy as np

from .errors import LadarError
from .names import RESULT_TAG


COLOR_ATTRIBUTE = "ladar_color"
COLOR_RGB_ATTRIBUTE = "ladar_rgb"

#: Colour ramp of the display (perceptually uniform, after matplotlib's viridis), linear RGB.
RAMP = ((0.0, (0.267, 0.005, 0.329)), (0.25, (0.229, 0.322, 0.546)), (0.5, (0.128, 0.567, 0.551)),
        (0.75, (0.369, 0.789, 0.383)), (1.0, (0.993, 0.906, 0.144)))

#: What the points can be coloured by: key → (point attribute, label, unit, scale).  Scales: "p99" = 0 … the
#: 99th percentile (a few glints do not darken the rest), "minmax" = the data's minimum … maximum, "count" =
#: whole numbers from 1 (or 0) … the maximum.  Unit None: the run's own (``metadata.json`` → ``units``, kept on
#: the object as ``ladar_unit_<attribute>`` by :func:`create_point_cloud`).
COLOR_BY = {
    "INTENSITY": ("intensity", "Intensity", None, "p99"),
    "RANGE": ("range_m", "Range", "m", "minmax"),
    "ECHO": ("echo_index", "Echo Number", "", "count"),
    "SNR": ("snr", "Detection SNR", "", "p99"),
    "FRAME": ("frame", "Frame", "", "minmax"),
    "CHANNEL": ("channel", "Channel", "", "minmax"),
}


# ------------------------------------------------------------------------------------------------------------
# Colour
# ------------------------------------------------------------------------------------------------------------
def intensity_norm(intensity: np.ndarray, percentile: float = 99.0) -> np.ndarray:
    """Intensity scaled to 0…1 by its ``percentile`` (clipped; a few glints do not darken the rest)."""
    intensity = np.asarray(intensity, dtype=np.float64)
    finite = intensity[np.isfinite(intensity)]
    top = float(np.percentile(finite, percentile)) if finite.size else 0.0
    if top <= 0.0:
        return np.zeros(intensity.shape, np.float32)
    return np.clip(np.nan_to_num(intensity / top, nan=0.0), 0.0, 1.0).astype(np.float32)


def color_scale(values: np.ndarray, scale: str) -> tuple[float, float]:
    """(value at the ramp's start, value at its end) for ``values`` on the scale kind of :data:`COLOR_BY`."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    if scale == "p99":
        lo, hi = 0.0, float(np.percentile(v, 99.0))
    elif scale == "count":
        lo, hi = min(1.0, float(v.min())), float(v.max())
    else:
        lo, hi = float(v.min()), float(v.max())
    if not hi > lo:
        hi = lo + 1.0
    return lo, hi


def color_values(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``values`` mapped linearly onto 0…1 (lo → 0, hi → 1), clipped; NaN → 0."""
    v = (np.asarray(values, dtype=np.float64) - lo) / (hi - lo)
    return np.clip(np.nan_to_num(v, nan=0.0), 0.0, 1.0).astype(np.float32)


def ramp_colors(values: np.ndarray) -> np.ndarray:
    """RGBA (n, 4) float32 of :data:`RAMP` at ``values`` in 0…1 (linear interpolation, as the Color Ramp)."""
    stops = np.array([p for p, _ in RAMP])
    rgb = np.array([c for _, c in RAMP])
    out = np.ones((len(values), 4), np.float32)
    for k in range(3):
        out[:, k] = np.interp(values, stops, rgb[:, k])
    return out


def available_color_by(obj) -> list[str]:
    """The :data:`COLOR_BY` keys this point cloud has the attribute for."""
    attrs = obj.data.attributes
    return [k for k, (attr, *_) in COLOR_BY.items() if attrs.get(attr) is not None]


def _read_attribute(mesh, name) -> np.ndarray:
    attr = mesh.attributes[name]
    dtype = {"INT": np.int32, "BOOLEAN": bool}.get(attr.data_type, np.float32)
    out = np.empty(len(attr.data), dtype)
    if len(out):
        attr.data.foreach_get("value", out)
    return out


def apply_color(obj, color_by: str) -> tuple[float, float]:
    """Colour a result point cloud by ``color_by`` (a :data:`COLOR_BY` key): writes ``ladar_color`` (0…1) and
    ``ladar_rgb`` and records the legend on the object.  Returns the values at the ramp's ends.

    Raises LadarError if the cloud lacks the attribute (e.g. SNR without the noisy receiver)."""
    if color_by not in COLOR_BY:
        raise LadarError(f"unknown colour attribute {color_by!r}: one of {', '.join(COLOR_BY)}")
    attr_name, label, unit, scale = COLOR_BY[color_by]
    if unit is None:
        unit = obj.get(f"ladar_unit_{attr_name}", "")
    mesh = obj.data
    if mesh.attributes.get(attr_name) is None:
        have = ", ".join(COLOR_BY[k][1] for k in available_color_by(obj))
        raise LadarError(f"the point cloud {obj.name!r} has no {label.lower()} attribute ({attr_name}); it can be "
                         f"coloured by: {have}")
    values = _read_attribute(mesh, attr_name).astype(np.float64)
    lo, hi = color_scale(values, scale)
    norm = color_values(values, lo, hi)
    if mesh.attributes.get(COLOR_ATTRIBUTE) is None:
        mesh.attributes.new(COLOR_ATTRIBUTE, "FLOAT", "POINT")
    if mesh.color_attributes.get(COLOR_RGB_ATTRIBUTE) is None:
        mesh.color_attributes.new(COLOR_RGB_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    # look both up again: adding an attribute may reallocate the layers and invalidate earlier references
    value_attr = mesh.attributes[COLOR_ATTRIBUTE]
    rgb_attr = mesh.color_attributes[COLOR_RGB_ATTRIBUTE]
    if len(norm):
        value_attr.data.foreach_set("value", norm)
        rgb_attr.data.foreach_set("color", ramp_colors(norm).ravel())
    mesh.color_attributes.active_color = rgb_attr
    mesh.update()
    obj["ladar_color_by"] = color_by
    obj["ladar_color_label"] = label + (f" ({unit})" if unit else "")
    obj["ladar_color_min"] = lo
    obj["ladar_color_max"] = hi
    return lo, hi


def result_objects(scene=None) -> list:
    """Result point clouds (objects tagged with the run they came from), of ``scene`` or of the file."""
    objs = scene.objects if scene is not None else bpy.data.objects
    return [o for o in objs if o.get(RESULT_TAG) is not None and o.type == "MESH"]


def recolor(objects, color_by: str) -> tuple[int, list[str]]:
    """Apply :func:`apply_color` to ``objects``; returns (number recoloured, names lacking the attribute)."""
    done, missing = 0, []
    for obj in objects:
        if COLOR_BY[color_by][0] in obj.data.attributes:
            apply_color(obj, color_by)
            done += 1
        else:
            missing.append(obj.name)
    return done, missing


def point_radius(obj) -> float | None:
    """The display radius (Blender units) of a result point cloud (None without the point modifier)."""
    mod = obj.modifiers.get("Ladar Points")
    if mod is None or mod.node_group is None:
        return None
    return float(mod[socket_identifier(mod.node_group, "Point Radius")])


def set_point_radius(objects, radius: float) -> int:
    """Set the display radius (Blender units) of result point clouds; returns how many were changed."""
    n = 0
    for obj in objects:
        mod = obj.modifiers.get("Ladar Points")
        if mod is None or mod.node_group is None:
            continue
        mod[socket_identifier(mod.node_group, "Point Radius")] = float(radius)
        obj.update_tag()
        n += 1
    return n


def socket_identifier(ng, name):
    for item in ng.interface.items_tree:
        if getattr(item, "item_type", "SOCKET") == "SOCKET" and item.in_out == "INPUT" and item.name == name:
            return item.identifier
    raise KeyError(name)

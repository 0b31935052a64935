"""Bring a run's results into Blender: point clouds coloured by a chosen attribute, and the images.

Point clouds
    A mesh of vertices only (one per echo), in the collection "Ladar Results" (a sequence's per-frame clouds in a
    child collection named after the run), with one point attribute per 1-D array of the run's points
    (``intensity``, ``range_m``, ``echo_index`` (1 = first echo), ``n_echoes``, ``time_s``, ``pixel_x``/``pixel_y``,
    ``frame``; ``snr`` with the noisy receiver; ``pulse_index``, ``channel``, ``gps_time_s`` … for the scanner),
    ``position_sensor`` where present, ``intensity_norm`` (intensity / its 99th percentile, clipped to 0…1), and
    the display value ``ladar_color`` (0…1) of the attribute chosen with ``Scene.ladar.color_by``
    (:data:`COLOR_BY`) plus its colour ``ladar_rgb``.  Blender has no float64 attributes: ``gps_time_s`` is
    stored relative to the object's custom property ``gps_time_offset_s`` so it keeps µs resolution.
    A Geometry Nodes modifier ("Ladar Point Cloud": Mesh to Points with a *Point Radius* input, then Set
    Material) shows the vertices as points with the material "Ladar Points", which maps ``ladar_color`` through a
    Color Ramp (the legend: the object's custom properties ``ladar_color_by``, ``ladar_color_min`` and
    ``ladar_color_max`` give the values at the ramp's ends).
Images
    ``range.exr``, ``intensity.exr``, ``energy.exr`` load as ``<run>.range`` … (Non-Color data) and their false
    colour previews ``range.png`` … as ``<run>.range.png``; gated slices (``slices/slice_0001.exr`` …) load as
    the image sequence ``<run>.slices`` (and ``<run>.slices.png``); a frame sequence's range/intensity/energy
    images (``images/range_0001.exr`` …, numbered by scene frame) load as image sequences ``<run>.range`` ….

Nothing is duplicated silently: results whose names exist are replaced only when asked (``replace``); the
caller picks new names otherwise (``ladar_addon.simulate``).  An import that fails half-way removes what it
created.
"""
from __future__ import annotations

import json
from pathlib import Path

import bpy
import numpy as np

from .errors import LadarError
from .names import RESULT_TAG

RESULTS_COLLECTION = "Ladar Results"
NODE_GROUP_NAME = "Ladar Point Cloud"
MATERIAL_NAME = "Ladar Points"
COLOR_ATTRIBUTE = "ladar_color"
COLOR_RGB_ATTRIBUTE = "ladar_rgb"
IMAGE_PRODUCTS = ("range", "intensity", "energy")

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
#: float64 point arrays stored relative to their minimum (object property ``<name>_offset``).
OFFSET_ATTRIBUTES = ("gps_time_s",)


# ------------------------------------------------------------------------------------------------------------
# Names
# ------------------------------------------------------------------------------------------------------------
def frame_run_name(run_name: str, frame: int) -> str:
    """Name of one frame's results inside a sequence run (its folder is ``frame_NNNN``)."""
    return f"{run_name}_frame_{frame:04d}"


def result_names(run_name: str, frames=None, clouds: str = "RUN") -> tuple[list[str], list[str]]:
    """(object names, image names) an import of run ``run_name`` creates; ``frames`` for a sequence run."""
    images = [f"{run_name}.{p}{ext}" for p in (*IMAGE_PRODUCTS, "slices") for ext in ("", ".png")]
    if frames is None:
        return [run_name], images
    images += [f"{frame_run_name(run_name, f)}.slices{ext}" for f in frames for ext in ("", ".png")]
    objects = [run_name] if clouds == "RUN" else [frame_run_name(run_name, f) for f in frames]
    return objects, images


def existing_results(run_name: str, frames=None, clouds: str = "RUN") -> list[str]:
    """Names of objects and images that an import of ``run_name`` would replace."""
    objects, images = result_names(run_name, frames, clouds)
    return [n for n in objects if bpy.data.objects.get(n) is not None] + \
        [n for n in images if bpy.data.images.get(n) is not None]


def check_result_names(run_name: str, overwrite: bool, frames=None, clouds: str = "RUN") -> None:
    """Raise LadarError if importing results named ``run_name`` would replace data and overwrite is off."""
    if overwrite:
        return
    taken = existing_results(run_name, frames, clouds)
    if taken:
        kind = "an object" if bpy.data.objects.get(taken[0]) is not None else "an image"
        raise LadarError(f"{kind} named {taken[0]!r} already exists: delete it, keep it by choosing a new run "
                         f"name (If Exists: New Name) or replace it (If Exists: Replace)")


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
    return float(mod[_socket_identifier(mod.node_group, "Point Radius")])


def set_point_radius(objects, radius: float) -> int:
    """Set the display radius (Blender units) of result point clouds; returns how many were changed."""
    n = 0
    for obj in objects:
        mod = obj.modifiers.get("Ladar Points")
        if mod is None or mod.node_group is None:
            continue
        mod[_socket_identifier(mod.node_group, "Point Radius")] = float(radius)
        obj.update_tag()
        n += 1
    return n


# ------------------------------------------------------------------------------------------------------------
# Display set-up
# ------------------------------------------------------------------------------------------------------------
def _results_collection(scene, child: str | None = None):
    coll = bpy.data.collections.get(RESULTS_COLLECTION)
    if coll is None:
        coll = bpy.data.collections.new(RESULTS_COLLECTION)
    if coll not in scene.collection.children_recursive:
        scene.collection.children.link(coll)
    if child is None:
        return coll
    sub = bpy.data.collections.get(child)
    if sub is None:
        sub = bpy.data.collections.new(child)
    if sub not in coll.children_recursive:
        coll.children.link(sub)
    return sub


def remove_run_objects(run_path) -> list[str]:
    """Remove the result point clouds imported from ``run_path`` (or one of its frame folders)."""
    root = Path(run_path).resolve()
    removed = []
    for obj in list(bpy.data.objects):
        tag = obj.get(RESULT_TAG)
        if tag is None:
            continue
        try:
            path = Path(str(tag)).resolve()
        except (OSError, RuntimeError):  # pragma: no cover - an unreadable tag
            continue
        if path == root or root in path.parents:
            removed.append(obj.name)
            _remove_object(obj)
    return removed


def _remove_object(obj):
    data = obj.data
    bpy.data.objects.remove(obj, do_unlink=True)
    if data is not None and data.users == 0:
        bpy.data.meshes.remove(data)


def ensure_point_material():
    """The "Ladar Points" material: Attribute(ladar_color) → Color Ramp → base + emission colour."""
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(MATERIAL_NAME)
    if mat.node_tree is None:  # Blender < 5.0: materials get a node tree on request
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_type = "GEOMETRY"
    attr.attribute_name = COLOR_ATTRIBUTE
    attr.location = (-700, 0)
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.name = ramp.label = "Ladar Legend"
    ramp.location = (-450, 0)
    elements = ramp.color_ramp.elements
    while len(elements) < len(RAMP):
        elements.new(0.5)
    for element, (pos, rgb) in zip(elements, RAMP):
        element.position = pos
        element.color = (*rgb, 1.0)
    bsdf = nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.location = (-100, 0)
    out = nodes.new("ShaderNodeOutputMaterial")
    out.location = (250, 0)
    links.new(attr.outputs["Fac"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    emission = bsdf.inputs.get("Emission Color") or bsdf.inputs.get("Emission")
    if emission is not None:
        links.new(ramp.outputs["Color"], emission)
    strength = bsdf.inputs.get("Emission Strength")
    if strength is not None:
        strength.default_value = 1.0
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    mat.diffuse_color = (*RAMP[2][1], 1.0)
    return mat


def legend_ramp_node():
    """The Color Ramp node of the point material (what the panel draws as the legend), or None."""
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is None or mat.node_tree is None:
        return None
    return mat.node_tree.nodes.get("Ladar Legend")


def ensure_point_node_group():
    """The "Ladar Point Cloud" Geometry Nodes group: Mesh to Points (radius input) → Set Material."""
    ng = bpy.data.node_groups.get(NODE_GROUP_NAME)
    if ng is not None and ng.bl_idname == "GeometryNodeTree":
        return ng
    ng = bpy.data.node_groups.new(NODE_GROUP_NAME, "GeometryNodeTree")
    if hasattr(ng, "is_modifier"):
        ng.is_modifier = True
    iface = ng.interface
    iface.new_socket(name="Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    radius = iface.new_socket(name="Point Radius", in_out="INPUT", socket_type="NodeSocketFloat")
    radius.default_value = 0.05
    radius.min_value = 0.0
    if hasattr(radius, "subtype"):
        radius.subtype = "DISTANCE"
    iface.new_socket(name="Material", in_out="INPUT", socket_type="NodeSocketMaterial")
    iface.new_socket(name="Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = ng.nodes, ng.links
    group_in = nodes.new("NodeGroupInput")
    group_in.location = (-500, 0)
    to_points = nodes.new("GeometryNodeMeshToPoints")
    to_points.location = (-200, 0)
    set_mat = nodes.new("GeometryNodeSetMaterial")
    set_mat.location = (50, 0)
    group_out = nodes.new("NodeGroupOutput")
    group_out.location = (300, 0)
    links.new(group_in.outputs["Geometry"], to_points.inputs["Mesh"])
    links.new(group_in.outputs["Point Radius"], to_points.inputs["Radius"])
    links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
    links.new(group_in.outputs["Material"], set_mat.inputs["Material"])
    links.new(set_mat.outputs["Geometry"], group_out.inputs["Geometry"])
    return ng


def _socket_identifier(ng, name):
    for item in ng.interface.items_tree:
        if getattr(item, "item_type", "SOCKET") == "SOCKET" and item.in_out == "INPUT" and item.name == name:
            return item.identifier
    raise KeyError(name)


# ------------------------------------------------------------------------------------------------------------
# Point clouds
# ------------------------------------------------------------------------------------------------------------
def _attribute_type(arr: np.ndarray):
    """(Blender attribute type, numpy dtype, foreach key) of a per-point array, or None to skip it."""
    if arr.ndim == 2 and arr.shape[1] == 3 and arr.dtype.kind == "f":
        return "FLOAT_VECTOR", np.float32, "vector"
    if arr.ndim != 1:
        return None
    if arr.dtype.kind == "b":
        return "BOOLEAN", bool, "value"
    if arr.dtype.kind in "iu":
        return "INT", np.int32, "value"
    if arr.dtype.kind == "f":
        return "FLOAT", np.float32, "value"
    return None


def create_point_cloud(name: str, points, scene, *, unit_scale: float = 1.0, replace: bool = False,
                       point_radius: float = 0.05, run_path=None, color_by: str = "INTENSITY", collection=None,
                       units: dict | None = None):
    """A vertices-only mesh object with the run's per-point attributes and the point display set-up.

    ``points``: a mapping of per-point arrays with ``position_world`` (n, 3) in metres (a run's points.npz).
    ``color_by`` falls back to intensity when the cloud lacks that attribute.  ``units``: the run's product
    units (``metadata.json`` → ``units``); the intensity's unit is kept on the object for the legend.
    """
    old = bpy.data.objects.get(name)
    if old is not None:
        if not replace:
            raise LadarError(f"an object named {name!r} already exists: enable overwrite to replace it")
        _remove_object(old)
    pos = np.asarray(points["position_world"], dtype=np.float64).reshape(-1, 3)
    n = len(pos)
    mesh = bpy.data.meshes.new(name)
    obj = None
    try:
        mesh.vertices.add(n)
        if n:
            mesh.attributes["position"].data.foreach_set("vector", (pos / unit_scale).astype(np.float32).ravel())
        offsets = {}
        for key in points.keys():
            if key == "position_world":
                continue
            arr = np.asarray(points[key])
            if len(arr) != n or key in mesh.attributes:
                continue
            kind = _attribute_type(arr)
            if kind is None:
                continue
            btype, dtype, field = kind
            if key in OFFSET_ATTRIBUTES and n:
                offsets[key] = float(np.nanmin(arr))
                arr = arr - offsets[key]
            attr = mesh.attributes.new(key, btype, "POINT")
            if n:
                attr.data.foreach_set(field, arr.astype(dtype).ravel())
        attr = mesh.attributes.new("intensity_norm", "FLOAT", "POINT")
        if n:
            attr.data.foreach_set("value", intensity_norm(np.asarray(points["intensity"]) if "intensity" in points
                                                          else np.zeros(n)))
        mesh.update()
        obj = bpy.data.objects.new(name, mesh)
        for key, offset in offsets.items():
            obj[f"{key.removesuffix('_s')}_offset_s" if key.endswith("_s") else f"{key}_offset"] = offset
        obj[RESULT_TAG] = str(run_path) if run_path is not None else name
        obj["ladar_unit_scale"] = float(unit_scale)  # metres per Blender unit of the positions
        if units and units.get("intensity"):
            obj["ladar_unit_intensity"] = units["intensity"]
        (collection or _results_collection(scene)).objects.link(obj)
        material = ensure_point_material()
        mesh.materials.append(material)
        ng = ensure_point_node_group()
        mod = obj.modifiers.new("Ladar Points", "NODES")
        mod.node_group = ng
        mod[_socket_identifier(ng, "Point Radius")] = float(point_radius)
        mod[_socket_identifier(ng, "Material")] = material
        apply_color(obj, color_by if COLOR_BY.get(color_by, ("",))[0] in mesh.attributes else "INTENSITY")
    except BaseException:
        if obj is not None:
            _remove_object(obj)
        elif mesh.users == 0:
            bpy.data.meshes.remove(mesh)
        raise
    return obj


# ------------------------------------------------------------------------------------------------------------
# Images
# ------------------------------------------------------------------------------------------------------------
def load_image(path, name: str, *, replace: bool = False, sequence: bool = False, data: bool = True):
    """Load an image file (the first file of a sequence when ``sequence``) as ``name``.

    ``data``: EXR values (Non-Color); PNG previews keep their sRGB colour space."""
    old = bpy.data.images.get(name)
    if old is not None:
        if not replace:
            raise LadarError(f"an image named {name!r} already exists: enable overwrite to replace it")
        bpy.data.images.remove(old)
    img = bpy.data.images.load(str(path), check_existing=False)
    img.name = name
    if sequence:
        img.source = "SEQUENCE"
    if data:
        try:
            img.colorspace_settings.name = "Non-Color"
        except TypeError:  # pragma: no cover - colour management without that space
            pass
    return img


def _load_run_images(run_path: Path, run_name: str, replace: bool) -> list:
    """range/intensity/energy EXRs + PNG previews, and the gated slices as image sequences."""
    images = []
    for product in IMAGE_PRODUCTS:
        for ext, data in ((".exr", True), (".png", False)):
            path = run_path / f"{product}{ext}"
            if path.is_file():
                images.append(load_image(path, f"{run_name}.{product}" + (".png" if ext == ".png" else ""),
                                         replace=replace, data=data))
    images += _load_slices(run_path, run_name, replace)
    return images


def _load_slices(run_path: Path, run_name: str, replace: bool) -> list:
    images = []
    for ext, data in ((".exr", True), (".png", False)):
        first = run_path / "slices" / f"slice_0001{ext}"
        if first.is_file():
            images.append(load_image(first, f"{run_name}.slices" + (".png" if ext == ".png" else ""),
                                     replace=replace, sequence=True, data=data))
    return images


def _load_points(path: Path) -> dict:
    with np.load(path) as npz:
        return {k: npz[k] for k in npz.files}


def read_run_info(run_path) -> dict:
    """The run folder's metadata.json (a frame run or a sequence: ``format`` "ladar-run"/"ladar-sequence")."""
    path = Path(run_path) / "metadata.json"
    if not path.is_file():
        raise LadarError(f"{run_path} is not a ladar run folder (no metadata.json)")
    return json.loads(path.read_text(encoding="utf-8"))


def import_run(run_path, scene, *, run_name: str | None = None, unit_scale: float = 1.0, replace: bool = False,
               point_radius: float = 0.05, color_by: str = "INTENSITY", clouds: str = "RUN"):
    """Point cloud object(s) and images of a finished run folder (one frame or a frame sequence).

    A sequence run gets one merged cloud (``clouds`` = "RUN", with a ``frame`` attribute) or one cloud per frame
    ("FRAME", in a child collection named after the run).  Returns (objects, images).  Nothing is left behind if
    it fails (names taken and ``replace`` off: LadarError before anything is created).
    """
    run_path = Path(run_path)
    run_name = run_name or run_path.name
    info = read_run_info(run_path)
    sequence = info.get("format") == "ladar-sequence"
    frames = [int(f) for f in info["frames"]] if sequence else None
    units = info.get("units", {})
    check_result_names(run_name, replace, frames, clouds)
    if replace:  # earlier imports of this run folder (under any name or cloud layout) are stale
        remove_run_objects(run_path)
    objects, images = [], []
    try:
        if not sequence:
            objects.append(create_point_cloud(run_name, _load_points(run_path / "points.npz"), scene,
                                              unit_scale=unit_scale, replace=replace, point_radius=point_radius,
                                              run_path=run_path, color_by=color_by, units=units))
            images += _load_run_images(run_path, run_name, replace)
        else:
            if clouds == "RUN":
                merged = run_path / "points_merged.npz"
                points = _load_points(merged) if merged.is_file() else {"position_world": np.zeros((0, 3))}
                objects.append(create_point_cloud(run_name, points, scene, unit_scale=unit_scale, replace=replace,
                                                  point_radius=point_radius, run_path=run_path,
                                                  color_by=color_by, units=units))
            else:
                coll = _results_collection(scene, run_name)
                for f in frames:
                    objects.append(create_point_cloud(
                        frame_run_name(run_name, f), _load_points(run_path / f"frame_{f:04d}" / "points.npz"),
                        scene, unit_scale=unit_scale, replace=replace, point_radius=point_radius,
                        run_path=run_path / f"frame_{f:04d}", color_by=color_by, collection=coll, units=units))
            images += _load_sequence_images(run_path, run_name, replace)
            for f in frames:
                images += _load_slices(run_path / f"frame_{f:04d}", frame_run_name(run_name, f), replace)
    except BaseException:
        for obj in objects:
            if obj.name in bpy.data.objects:
                _remove_object(obj)
        for img in images:
            if img.name in bpy.data.images:
                bpy.data.images.remove(img)
        raise
    return objects, images


def _load_sequence_images(run_path: Path, run_name: str, replace: bool) -> list:
    images = []
    folder = run_path / "images"
    for product in IMAGE_PRODUCTS:
        for ext, data in ((".exr", True), (".png", False)):
            files = sorted(folder.glob(f"{product}_[0-9][0-9][0-9][0-9]{ext}")) if folder.is_dir() else []
            if files:
                images.append(load_image(files[0], f"{run_name}.{product}" + (".png" if ext == ".png" else ""),
                                         replace=replace, sequence=True, data=data))
    return images


# ------------------------------------------------------------------------------------------------------------
# Waveform view
# ------------------------------------------------------------------------------------------------------------
def frame_run_folder(run_path, frame: int | None = None) -> Path:
    """The run folder of one frame: ``run_path`` itself, or for a sequence its ``frame_NNNN`` (``frame``, else
    the first frame)."""
    run_path = Path(run_path)
    info = read_run_info(run_path)
    if info.get("format") != "ladar-sequence":
        return run_path
    frames = [int(f) for f in info["frames"]]
    if frame is None or frame not in frames:
        frame = frames[0]
    return run_path / f"frame_{frame:04d}"


def waveform_plot(run_path, *, pixel_x: int | None = None, pixel_y: int | None = None, pulse: int | None = None,
                  frame: int | None = None) -> tuple[Path, dict]:
    """Plot one waveform of a run as a PNG in ``<run>/previews/`` (a new file; an existing plot of the same
    waveform is reused, never replaced).  Returns (png path, what was plotted).

    Image runs (flash, profiler): the waveform of pixel (``pixel_x``, ``pixel_y``), default (0, 0) — the range
    profiler's one waveform.  Scanner runs: pulse ``pulse``, default the pulse that received the most energy.
    The echoes detected on it are marked.  Raises LadarError when the run saved no waveforms."""
    from ..core.errors import ConfigError
    from ..core.fileio.preview import bin_centres_range_m, waveform_png

    folder = frame_run_folder(run_path, frame)
    info = read_run_info(folder)
    wf_file = folder / "waveforms.npy"
    if not wf_file.is_file():
        raise LadarError(f"the run {folder} has no waveforms.npy: enable Run > Save Waveforms and simulate again")
    cube = np.load(wf_file, mmap_mode="r")
    points = _load_points(folder / "points.npz") if (folder / "points.npz").is_file() else {}
    if cube.ndim == 3:
        h, w, n_bins = cube.shape
        x = 0 if pixel_x is None else int(pixel_x)
        y = 0 if pixel_y is None else int(pixel_y)
        if not 0 <= x < w:
            raise ConfigError("pixel_x", x, f"a column of the {w}×{h} receiver: 0 … {w - 1}")
        if not 0 <= y < h:
            raise ConfigError("pixel_y", y, f"a row of the {w}×{h} receiver: 0 … {h - 1}")
        values = np.asarray(cube[y, x], dtype=np.float64)
        mine = ((points.get("pixel_x", np.zeros(0)) == x) & (points.get("pixel_y", np.zeros(0)) == y)) \
            if points else np.zeros(0, bool)
        what = {"pixel_x": x, "pixel_y": y}
        name = f"waveform_x{x:04d}_y{y:04d}.png"
        title = "Range profile" if (h, w) == (1, 1) else f"Waveform of pixel ({x}, {y})"
    elif cube.ndim == 2:
        n_pulses, n_bins = cube.shape
        p = int(np.argmax(np.asarray(cube).sum(axis=1))) if pulse is None else int(pulse)
        if not 0 <= p < n_pulses:
            raise ConfigError("pulse", p, f"a pulse of the scan: 0 … {n_pulses - 1}")
        values = np.asarray(cube[p], dtype=np.float64)
        mine = (points.get("pulse_index", np.zeros(0)) == p) if points else np.zeros(0, bool)
        what = {"pulse": p}
        name = f"waveform_pulse{p:08d}.png"
        title = f"Waveform of pulse {p}"
    else:
        raise LadarError(f"{wf_file} has an unexpected shape {cube.shape}")
    gate = info["settings"]["gate"]
    range_m = bin_centres_range_m(gate["gate_start_s"], gate["bin_width_s"], n_bins)
    echoes_m = np.asarray(points["range_m"])[mine] if points and mine.any() else np.zeros(0)
    what.update({"frame": info.get("frame"), "n_bins": int(n_bins), "peak_j": float(values.max()),
                 "energy_j": float(values.sum()), "echo_ranges_m": [float(r) for r in echoes_m]})
    out = folder / "previews" / name
    if not out.exists():
        waveform_png(out, range_m, values, title=title, markers_m=echoes_m)
    return out, what


def show_waveform(run_path, run_name: str | None = None, **kwargs):
    """:func:`waveform_plot`, loaded as the image ``<run>.waveform`` (replacing that view).  Returns
    (image, what was plotted)."""
    path, what = waveform_plot(run_path, **kwargs)
    name = f"{run_name or Path(run_path).name}.waveform"
    img = load_image(path, name, replace=True, data=False)
    img.reload()
    return img, what

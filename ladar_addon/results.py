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
from .colors import COLOR_ATTRIBUTE, COLOR_BY, RAMP, apply_color, intensity_norm, socket_identifier
from .names import RESULT_TAG

RESULTS_COLLECTION = "Ladar Results"
NODE_GROUP_NAME = "Ladar Point Cloud"
MATERIAL_NAME = "Ladar Points"
IMAGE_PRODUCTS = ("range", "intensity", "energy")

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
        mod[socket_identifier(ng, "Point Radius")] = float(point_radius)
        mod[socket_identifier(ng, "Material")] = material
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


def load_points(path: Path) -> dict:
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
            objects.append(create_point_cloud(run_name, load_points(run_path / "points.npz"), scene,
                                              unit_scale=unit_scale, replace=replace, point_radius=point_radius,
                                              run_path=run_path, color_by=color_by, units=units))
            images += _load_run_images(run_path, run_name, replace)
        else:
            if clouds == "RUN":
                merged = run_path / "points_merged.npz"
                points = load_points(merged) if merged.is_file() else {"position_world": np.zeros((0, 3))}
                objects.append(create_point_cloud(run_name, points, scene, unit_scale=unit_scale, replace=replace,
                                                  point_radius=point_radius, run_path=run_path,
                                                  color_by=color_by, units=units))
            else:
                coll = _results_collection(scene, run_name)
                for f in frames:
                    objects.append(create_point_cloud(
                        frame_run_name(run_name, f), load_points(run_path / f"frame_{f:04d}" / "points.npz"),
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



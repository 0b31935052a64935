"""Bring a run's results into Blender: a point-cloud object coloured by intensity, and the images.

* The point cloud is a mesh of vertices only (one per echo) named after the run, in the collection
  "Ladar Results", with point attributes ``intensity``, ``range_m``, ``echo_index`` (1 = first echo),
  ``n_echoes``, ``time_s``, ``pixel_x``, ``pixel_y``, ``frame``, ``position_sensor`` and ``intensity_norm``
  (intensity / its 99th percentile, clipped to 0…1), plus the colour attribute ``intensity_color``.
* A Geometry Nodes modifier ("Ladar Point Cloud" group: Mesh to Points with a *Point Radius* input, then Set
  Material) turns the vertices into points with the material "Ladar Intensity", which reads
  ``intensity_norm`` through an Attribute node and a Color Ramp into the base and emission colour.
* ``range.exr``, ``intensity.exr`` and ``energy.exr`` are loaded as images ``<run>.range`` etc.

An existing object or image of the same name is replaced only when ``overwrite`` is true; otherwise
:class:`LadarError` is raised (call :func:`check_result_names` before a run to fail before any work).
"""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from .errors import LadarError
from .export import RESULT_TAG

RESULTS_COLLECTION = "Ladar Results"
NODE_GROUP_NAME = "Ladar Point Cloud"
MATERIAL_NAME = "Ladar Intensity"
IMAGE_PRODUCTS = ("range", "intensity", "energy")

#: Colour ramp of the intensity display (perceptually uniform, after matplotlib's viridis), linear RGB.
RAMP = ((0.0, (0.267, 0.005, 0.329)), (0.25, (0.229, 0.322, 0.546)), (0.5, (0.128, 0.567, 0.551)),
        (0.75, (0.369, 0.789, 0.383)), (1.0, (0.993, 0.906, 0.144)))

# name → (Blender attribute type, numpy dtype)
POINT_ATTRIBUTES = {"intensity": ("FLOAT", np.float32), "range_m": ("FLOAT", np.float32),
                    "echo_index": ("INT", np.int32), "n_echoes": ("INT", np.int32),
                    "time_s": ("FLOAT", np.float32), "pixel_x": ("INT", np.int32),
                    "pixel_y": ("INT", np.int32), "frame": ("INT", np.int32)}


def image_names(run_name: str) -> list[str]:
    return [f"{run_name}.{p}" for p in IMAGE_PRODUCTS]


def check_result_names(run_name: str, overwrite: bool) -> None:
    """Raise LadarError if importing results named ``run_name`` would replace data and overwrite is off."""
    if overwrite:
        return
    if bpy.data.objects.get(run_name) is not None:
        raise LadarError(f"an object named {run_name!r} already exists: delete it, choose another run name or "
                         f"enable overwrite")
    for name in image_names(run_name):
        if bpy.data.images.get(name) is not None:
            raise LadarError(f"an image named {name!r} already exists: delete it, choose another run name or "
                             f"enable overwrite")


def intensity_norm(intensity: np.ndarray, percentile: float = 99.0) -> np.ndarray:
    """Intensity scaled to 0…1 by its ``percentile`` (clipped; a few glints do not darken the rest)."""
    intensity = np.asarray(intensity, dtype=np.float64)
    finite = intensity[np.isfinite(intensity)]
    top = float(np.percentile(finite, percentile)) if finite.size else 0.0
    if top <= 0.0:
        return np.zeros(intensity.shape, np.float32)
    return np.clip(np.nan_to_num(intensity / top, nan=0.0), 0.0, 1.0).astype(np.float32)


def ramp_colors(values: np.ndarray) -> np.ndarray:
    """RGBA (n, 4) float32 of :data:`RAMP` at ``values`` in 0…1 (linear interpolation, as the Color Ramp)."""
    stops = np.array([p for p, _ in RAMP])
    rgb = np.array([c for _, c in RAMP])
    out = np.ones((len(values), 4), np.float32)
    for k in range(3):
        out[:, k] = np.interp(values, stops, rgb[:, k])
    return out


def _results_collection(scene):
    coll = bpy.data.collections.get(RESULTS_COLLECTION)
    if coll is None:
        coll = bpy.data.collections.new(RESULTS_COLLECTION)
    if scene.collection.children.get(coll.name) is None and coll not in scene.collection.children_recursive:
        scene.collection.children.link(coll)
    return coll


def _remove_object(obj):
    data = obj.data
    bpy.data.objects.remove(obj, do_unlink=True)
    if data is not None and data.users == 0:
        bpy.data.meshes.remove(data)


def ensure_point_material():
    """The "Ladar Intensity" material: Attribute(intensity_norm) → Color Ramp → base + emission colour."""
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
    attr.attribute_name = "intensity_norm"
    attr.location = (-700, 0)
    ramp = nodes.new("ShaderNodeValToRGB")
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


def create_point_cloud(name: str, points: dict, scene, *, unit_scale: float = 1.0, overwrite: bool = False,
                       point_radius: float = 0.05, run_path: str | None = None):
    """A vertices-only mesh object with the run's per-point attributes and the point display set-up."""
    old = bpy.data.objects.get(name)
    if old is not None:
        if not overwrite:
            raise LadarError(f"an object named {name!r} already exists: enable overwrite to replace it")
        _remove_object(old)
    pos = np.asarray(points["position_world"], dtype=np.float64).reshape(-1, 3)
    n = len(pos)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(n)
    if n:
        mesh.attributes["position"].data.foreach_set("vector", (pos / unit_scale).astype(np.float32).ravel())
    for key, (btype, dtype) in POINT_ATTRIBUTES.items():
        if key not in points:
            continue
        attr = mesh.attributes.new(key, btype, "POINT")
        if n:
            attr.data.foreach_set("value", np.asarray(points[key]).astype(dtype).ravel())
    if "position_sensor" in points:
        attr = mesh.attributes.new("position_sensor", "FLOAT_VECTOR", "POINT")
        if n:
            attr.data.foreach_set("vector", np.asarray(points["position_sensor"], np.float32).ravel())
    norm = intensity_norm(points.get("intensity", np.zeros(n)))
    attr = mesh.attributes.new("intensity_norm", "FLOAT", "POINT")
    color = mesh.color_attributes.new("intensity_color", "FLOAT_COLOR", "POINT")
    if n:
        attr.data.foreach_set("value", norm)
        color.data.foreach_set("color", ramp_colors(norm).ravel())
    mesh.color_attributes.active_color = color
    mesh.update()

    obj = bpy.data.objects.new(name, mesh)
    obj[RESULT_TAG] = str(run_path) if run_path is not None else name
    _results_collection(scene).objects.link(obj)
    material = ensure_point_material()
    mesh.materials.append(material)
    ng = ensure_point_node_group()
    mod = obj.modifiers.new("Ladar Points", "NODES")
    mod.node_group = ng
    mod[_socket_identifier(ng, "Point Radius")] = float(point_radius)
    mod[_socket_identifier(ng, "Material")] = material
    return obj


def load_images(run_path, run_name: str, *, overwrite: bool = False) -> list:
    """Load the run's EXR images as ``<run>.range``, ``<run>.intensity``, ``<run>.energy`` (Non-Color)."""
    images = []
    for product, name in zip(IMAGE_PRODUCTS, image_names(run_name)):
        path = Path(run_path) / f"{product}.exr"
        if not path.is_file():
            continue
        old = bpy.data.images.get(name)
        if old is not None:
            if not overwrite:
                raise LadarError(f"an image named {name!r} already exists: enable overwrite to replace it")
            bpy.data.images.remove(old)
        img = bpy.data.images.load(str(path), check_existing=False)
        img.name = name
        try:
            img.colorspace_settings.name = "Non-Color"
        except TypeError:  # pragma: no cover - colour management without that space
            pass
        images.append(img)
    return images


def import_run(run_path, result, scene, *, run_name: str | None = None, unit_scale: float = 1.0,
               overwrite: bool = False, point_radius: float = 0.05):
    """Point cloud object + images of a finished run.  Returns (object, [images])."""
    run_name = run_name or Path(run_path).name
    check_result_names(run_name, overwrite)
    obj = create_point_cloud(run_name, result.points, scene, unit_scale=unit_scale, overwrite=overwrite,
                             point_radius=point_radius, run_path=run_path)
    images = load_images(run_path, run_name, overwrite=overwrite)
    return obj, images

"""Scene geometry for the simulator: Blender's evaluated depsgraph → world-space triangles with materials.

What is exported (:func:`scene_geometry_from_depsgraph`):

* every object the depsgraph lists in ``object_instances`` — objects in collections enabled in the view layer,
  not disabled in viewports (monitor icon) and not hidden (eye icon) — that is also enabled for renders
  (camera icon: ``hide_render`` off, on the object and on the instancer of an instance);
* meshes **after modifiers** (including Geometry Nodes), in world coordinates;
* **instances** of every kind (collection instances, Geometry Nodes instances, vertex/face instancing,
  particles) — each is flattened: the prototype's arrays are computed once per evaluated mesh and transformed
  by ``instance.matrix_world``;
* curves, surfaces, text and metaballs: their evaluated mesh, which the depsgraph lists as a mesh component
  "instance" of the object itself (so instanced text and curves work too);
* *not* exported: point clouds, hair curves, volumes, grease pencil, empties, cameras, lights, objects
  listed in ``exclude``, and the result point clouds of earlier runs (custom property ``ladar_run``).

Faces become triangles by a vectorized fan (triangles and quads; quads are split along the 0–2 diagonal).
A mesh with any face of more than four corners is triangulated by Blender (``loop_triangles``) instead.
Each triangle gets the material of its face (``material_index`` attribute, clamped to the object's last slot,
as Blender does) — the BRDF of ``Material.ladar_brdf`` when enabled, else the core default BRDF.

Coordinates are converted to metres with the scene's unit scale (``scale_length``).
"""
from __future__ import annotations

import dataclasses
import hashlib

import bpy
import numpy as np

from ..core.geometry.scene import SceneGeometry, merge_meshes
from .blend_config import brdf_from_material, material_key
from .names import RESULT_TAG

#: Custom property that marks result point clouds (never exported as geometry).

_EMPTY = (np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.int32))


def _foreach_get(collection_or_data, key, n, dtype, width=1):
    buf = np.empty(n * width, dtype=dtype)
    if n:
        collection_or_data.foreach_get(key, buf)
    return buf.reshape(-1, width) if width > 1 else buf


def mesh_arrays(mesh):
    """Local-space arrays of a mesh: (vertices (n, 3) float64, triangles (m, 3) int32, face material index (m,)).

    Uses the fast attribute paths: positions from the ``position`` attribute, corners from ``.corner_vert``
    and face starts from ``polygons.loop_start`` (skipped when every face is a triangle).
    """
    n_vert, n_face, n_corner = len(mesh.vertices), len(mesh.polygons), len(mesh.loops)
    if n_face == 0 or n_vert == 0:
        return _EMPTY
    attrs = mesh.attributes
    position = attrs.get("position")
    if position is not None:
        verts = _foreach_get(position.data, "vector", n_vert, np.float32, 3)
    else:  # pragma: no cover - every mesh of Blender ≥ 3.5 has the attribute
        verts = _foreach_get(mesh.vertices, "co", n_vert, np.float32, 3)
    corner_attr = attrs.get(".corner_vert")
    if corner_attr is not None:
        corner_vert = _foreach_get(corner_attr.data, "value", n_corner, np.int32)
    else:  # pragma: no cover - Blender < 4.0
        corner_vert = _foreach_get(mesh.loops, "vertex_index", n_corner, np.int32)
    mat_attr = attrs.get("material_index")
    if mat_attr is not None and mat_attr.domain == "FACE":
        face_material = _foreach_get(mat_attr.data, "value", n_face, np.int32)
    else:
        face_material = np.zeros(n_face, np.int32)

    if n_corner == 3 * n_face:  # every face has at least 3 corners, so all are triangles
        return verts.astype(np.float64), corner_vert.reshape(-1, 3), face_material
    loop_start = _foreach_get(mesh.polygons, "loop_start", n_face, np.int32)
    corners = np.diff(np.append(loop_start, n_corner))
    if corners.max() > 4:
        return _loop_triangle_arrays(mesh, verts, face_material)
    # Fan triangulation: face f with k corners → triangles (c0, c_j+1, c_j+2), j = 0 … k-3.
    tris_per_face = corners - 2
    n_tri = int(tris_per_face.sum())
    face_of_tri = np.repeat(np.arange(n_face, dtype=np.int64), tris_per_face)
    first_tri = np.repeat(np.cumsum(tris_per_face) - tris_per_face, tris_per_face)
    j = np.arange(n_tri, dtype=np.int64) - first_tri
    start = loop_start[face_of_tri].astype(np.int64)
    tris = np.stack([corner_vert[start], corner_vert[start + j + 1], corner_vert[start + j + 2]], axis=1)
    return verts.astype(np.float64), tris.astype(np.int32, copy=False), face_material[face_of_tri]


def _loop_triangle_arrays(mesh, verts, face_material):
    """Fallback for meshes with n-gons (> 4 corners): Blender's own triangulation."""
    tris_rna = mesh.loop_triangles
    n_tri = len(tris_rna)
    tris = _foreach_get(tris_rna, "vertices", n_tri, np.int32, 3)
    face = _foreach_get(tris_rna, "polygon_index", n_tri, np.int32)
    return verts.astype(np.float64), tris, face_material[face]


def _slot_materials(obj, mesh):
    """Materials of the object's slots (falling back to the mesh's own list), original datablocks."""
    mats = [slot.material for slot in obj.material_slots] if len(obj.material_slots) else list(mesh.materials)
    return [None if m is None else m.original for m in mats]


def _material_table(materials):
    names = ["default" if m is None else material_key(m) for m in materials]
    brdfs = [brdf_from_material(m) for m in materials]
    return names, brdfs


def _hidden_for_render(inst) -> bool:
    if inst.object.original.hide_render:
        return True
    parent = inst.parent if inst.is_instance else None
    return parent is not None and parent.original.hide_render


def scene_geometry_from_depsgraph(depsgraph, *, unit_scale: float | None = None, exclude=(),
                                  stats: dict | None = None) -> SceneGeometry:
    """Triangles of every visible object of an evaluated depsgraph in world coordinates (metres).

    ``unit_scale``: metres per Blender unit (default: the scene's ``scale_length``, 1 without a unit system).
    ``exclude``: names of objects to leave out.  ``stats`` (a dict) receives counts of what was exported.
    """
    if unit_scale is None:
        us = depsgraph.scene.unit_settings
        unit_scale = 1.0 if us.system == "NONE" else float(us.scale_length)
    exclude = set(exclude)
    cache = {}  # evaluated mesh pointer → local arrays
    parts = []
    counts = {"objects": 0, "instances": 0}
    for inst in depsgraph.object_instances:
        obj = inst.object
        if obj.type != "MESH":  # curve-like objects: their mesh comes as a separate MESH entry
            continue
        if not inst.show_self or _hidden_for_render(inst):
            continue
        original = obj.original
        if original.name in exclude or original.get(RESULT_TAG) is not None:
            continue
        mesh = obj.data
        key = mesh.as_pointer()
        arrays = cache.get(key)
        if arrays is None:
            arrays = cache[key] = mesh_arrays(mesh)
        verts, tris, local_ids = arrays
        if len(tris) == 0:
            continue
        m = np.array(inst.matrix_world, dtype=np.float64)
        world = verts @ m[:3, :3].T + m[:3, 3]
        if unit_scale != 1.0:
            world *= unit_scale
        parts.append((world, tris, local_ids, *_material_table(_slot_materials(obj, mesh))))
        # the mesh of a curve/text/metaball object is listed as an "instance" of that same object
        own = not inst.is_instance or (inst.parent is not None and inst.parent.original == original)
        counts["objects" if own else "instances"] += 1
    n_objects, n_instances = counts["objects"], counts["instances"]
    geometry = merge_meshes(parts)
    if stats is not None:
        stats.update({"objects": n_objects, "instances": n_instances, "unique_meshes": len(cache),
                      "triangles": geometry.n_triangles, "vertices": int(len(geometry.vertices_m)),
                      "unit_scale_m": unit_scale})
    return geometry


# ------------------------------------------------------------------------------------------------------------
# Frame ranges: does the exported geometry change from frame to frame?
# ------------------------------------------------------------------------------------------------------------
#: Modifiers whose result depends only on their own settings and the object's mesh (when neither is animated
#: and no object pointer is set, they give the same geometry on every frame).
SELF_CONTAINED_MODIFIERS = {"SUBSURF", "MIRROR", "ARRAY", "BEVEL", "SOLIDIFY", "TRIANGULATE", "DECIMATE", "WELD",
                            "EDGE_SPLIT", "SMOOTH", "WEIGHTED_NORMAL", "REMESH", "SKIN", "WIREFRAME", "SCREW",
                            "MULTIRES", "DISPLACE", "CAST", "SIMPLE_DEFORM", "BOOLEAN"}


def animated(id_block) -> bool:
    anim = getattr(id_block, "animation_data", None) if id_block is not None else None
    return anim is not None and (anim.action is not None or len(anim.drivers) > 0 or len(anim.nla_tracks) > 0)


def _modifier_may_change(mod) -> bool:
    if mod.type not in SELF_CONTAINED_MODIFIERS:
        return True  # Geometry Nodes (Scene Time), armature, physics, particles, hooks, ...
    for prop in mod.bl_rna.properties:  # an object or texture pointer: the other datablock may move/animate
        if prop.type == "POINTER" and prop.identifier not in ("rna_type",):
            value = getattr(mod, prop.identifier, None)
            if isinstance(value, bpy.types.ID):
                return True
    return False


def _object_time_reasons(obj) -> list[str]:
    reasons = []
    if animated(obj):
        reasons.append("animated")
    data = obj.data
    if animated(data):
        reasons.append("animated data")
    keys = getattr(data, "shape_keys", None)
    if animated(keys):
        reasons.append("animated shape keys")
    if len(obj.constraints):
        reasons.append("constraints")
    if obj.rigid_body is not None:
        reasons.append("rigid body")
    if len(getattr(obj, "particle_systems", ())):
        reasons.append("particles")
    if any(_modifier_may_change(m) for m in obj.modifiers):
        reasons.append("time-dependent modifier")
    for slot in obj.material_slots:
        if slot.material is not None and animated(slot.material):
            reasons.append("animated material")
            break
    return reasons


def frame_dependent_objects(scene, depsgraph=None, exclude=()) -> dict:
    """Objects whose exported geometry (or BRDF) *may* change with the frame: {name: [reasons]}.

    Conservative: animation data (object, object data, shape keys, material), drivers, constraints, rigid
    bodies, particles and every modifier outside :data:`SELF_CONTAINED_MODIFIERS` (Geometry Nodes may read the
    scene time) count, for the object and every parent and instancer.  An empty result means one export serves
    every frame; otherwise the caller re-exports each frame and compares :func:`geometry_digest`.
    """
    exclude = set(exclude)
    candidates = [o for o in scene.objects if o.name not in exclude and o.get(RESULT_TAG) is None]
    if depsgraph is not None:
        for inst in depsgraph.object_instances:
            candidates.append(inst.object.original)
            if inst.is_instance and inst.parent is not None:
                candidates.append(inst.parent.original)
    found, seen = {}, set()
    for obj in candidates:
        chain = obj
        while chain is not None:
            if chain.name_full in seen:
                break
            seen.add(chain.name_full)
            if chain.name not in exclude and chain.get(RESULT_TAG) is None:
                reasons = _object_time_reasons(chain)
                if reasons:
                    found[chain.name] = reasons
            chain = chain.parent
    if animated(scene) or animated(scene.world):
        found["<scene>"] = ["animated scene or world (drivers may move anything)"]
    if scene.rigidbody_world is not None:
        found["<scene>"] = found.get("<scene>", []) + ["rigid body world"]
    return found


def geometry_digest(geometry: SceneGeometry) -> str:
    """A hash of the geometry and materials (equal digests: the same BVH and the same radiometry)."""
    h = hashlib.blake2b(digest_size=16)
    for arr in (geometry.vertices_m, geometry.triangles, geometry.material_ids):
        h.update(str(arr.shape).encode())
        h.update(np.ascontiguousarray(arr).tobytes())
    for name, brdf in zip(geometry.material_names, geometry.materials):
        h.update(name.encode())
        for f in dataclasses.fields(brdf):
            value = getattr(brdf, f.name)
            if isinstance(value, (np.ndarray, list, tuple)):  # measured tables: every value, not a repr
                h.update(np.asarray(value, dtype=np.float64).tobytes())
            else:
                h.update(repr(value).encode())
    return h.hexdigest()

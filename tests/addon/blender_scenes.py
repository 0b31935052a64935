"""Small scene builders for the add-on tests (no operators: plain data API)."""
from __future__ import annotations

import math

import bpy


def add_camera(scene, name="Ladar", location=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0), width_px=16,
               height_px=16, fov_rad=None, sensor_fit="AUTO", set_scene_camera=True):
    """A perspective camera object carrying ladar settings; ``fov_rad`` sets the angle of the fitted side."""
    cam = bpy.data.cameras.new(name)
    cam.sensor_fit = sensor_fit
    if fov_rad is not None:
        size = cam.sensor_height if sensor_fit == "VERTICAL" else cam.sensor_width
        cam.lens = 0.5 * size / math.tan(0.5 * fov_rad)
    obj = bpy.data.objects.new(name, cam)
    obj.location = location
    obj.rotation_euler = rotation
    scene.collection.objects.link(obj)
    obj.ladar.receiver.width_px = width_px
    obj.ladar.receiver.height_px = height_px
    if set_scene_camera:
        scene.camera = obj
    return obj


def add_mesh(scene, name, verts, faces, location=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0), collection=None,
             materials=(), face_materials=None):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in verts], [], [tuple(f) for f in faces])
    for m in materials:
        mesh.materials.append(m)
    if face_materials is not None:
        mesh.polygons.foreach_set("material_index", list(face_materials))
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = rotation
    (collection or scene.collection).objects.link(obj)
    return obj


def add_plate(scene, name="Plate", size=2.0, location=(0.0, 0.0, -100.0), rotation=(0.0, 0.0, 0.0),
              materials=(), collection=None):
    """A square plate in its local XY plane (normal +Z), facing a camera that looks along −Z."""
    h = 0.5 * size
    return add_mesh(scene, name, [(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [(0, 1, 2, 3)],
                    location, rotation, collection, materials)


CUBE_VERTS = [(-1, -1, -1), (1, -1, -1), (1, 1, -1), (-1, 1, -1), (-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)]
CUBE_FACES = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]


def add_cube(scene, name="Cube", **kwargs):
    """A 2 m cube (6 quads = 12 triangles) centred on its origin."""
    return add_mesh(scene, name, CUBE_VERTS, CUBE_FACES, **kwargs)


def brdf_material(name, **settings):
    """A material with ladar BRDF settings enabled."""
    mat = bpy.data.materials.new(name)
    mat.ladar_brdf.enabled = True
    for key, value in settings.items():
        setattr(mat.ladar_brdf, key, value)
    return mat

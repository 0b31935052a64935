"""A one-command preview render of result point clouds (Cycles, CPU) to a PNG, for reports.

The user's scene is not touched: a temporary scene links the point-cloud objects, gets its own camera (looking
at the clouds' bounding box from above-front-right, the whole box in view), a dark world and small Cycles
settings; it is rendered with ``bpy.ops.render.render(scene=...)`` and removed again (also on failure).  The PNG
is written atomically and an existing file is never replaced unless asked.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

from ..core.fileio.run_folder import new_temp_file
from .errors import LadarError

PREVIEW_RESOLUTION = (640, 480)
PREVIEW_SAMPLES = 16
#: Viewing direction from the clouds' centre towards the camera (right, front, up in world axes).
VIEW_DIRECTION = (0.55, -0.65, 0.52)
CAMERA_ANGLE_RAD = math.radians(40.0)


def _world_points(obj) -> np.ndarray:
    mesh = obj.data
    n = len(mesh.vertices)
    pos = np.empty(n * 3, np.float32)
    if n:
        mesh.attributes["position"].data.foreach_get("vector", pos)
    pos = pos.reshape(-1, 3).astype(np.float64)
    m = np.array(obj.matrix_world, dtype=np.float64)
    return pos @ m[:3, :3].T + m[:3, 3]


def framing_camera(points: np.ndarray, aspect: float, angle_rad: float = CAMERA_ANGLE_RAD,
                   direction=VIEW_DIRECTION):
    """(world matrix, distance, radius) of a camera that sees every point: it looks at the centre of the
    points' bounding box along ``-direction``, from the distance at which the box's bounding sphere fits the
    smaller field of view with a 10 % margin.  ``angle_rad`` is the camera angle of the longer image side."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
    half = 0.5 * angle_rad if aspect >= 1.0 else math.atan(math.tan(0.5 * angle_rad) * aspect)
    distance = 1.1 * radius / math.sin(half)
    d = Vector(direction).normalized()
    location = Vector(centre) + d * distance
    rot = (-d).to_track_quat("-Z", "Y").to_matrix().to_4x4()
    return Matrix.Translation(location) @ rot, distance, radius


def render_preview(objects, path, *, resolution=PREVIEW_RESOLUTION, samples: int = PREVIEW_SAMPLES,
                   overwrite: bool = False) -> Path:
    """Render ``objects`` (result point clouds) with Cycles on the CPU into the PNG ``path``; returns it."""
    objects = [o for o in objects if o is not None and o.type == "MESH" and len(o.data.vertices)]
    if not objects:
        raise LadarError("nothing to render: no result point cloud with points (simulate first, or select one)")
    path = Path(path)
    if path.exists() and not overwrite:
        raise LadarError(f"{path} exists: choose another file or allow replacing it")
    points = np.concatenate([_world_points(o) for o in objects])
    width, height = int(resolution[0]), int(resolution[1])
    scene = bpy.data.scenes.new("Ladar Preview Render")
    cam_data = bpy.data.cameras.new("Ladar Preview Camera")
    cam = bpy.data.objects.new("Ladar Preview Camera", cam_data)
    world = bpy.data.worlds.new("Ladar Preview World")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = new_temp_file(path.parent, f".{path.stem}.", ".png")
    os.close(fd)
    try:
        for obj in objects:
            scene.collection.objects.link(obj)
        scene.collection.objects.link(cam)
        cam_data.sensor_fit = "AUTO"
        cam_data.angle = CAMERA_ANGLE_RAD
        matrix, distance, radius = framing_camera(points, width / height)
        cam.matrix_world = matrix
        cam_data.clip_start = max(1e-3, 0.01 * (distance - radius))
        cam_data.clip_end = 2.0 * (distance + radius)
        scene.camera = cam
        world.color = (0.02, 0.02, 0.025)
        scene.world = world
        scene.render.engine = "CYCLES"
        scene.cycles.device = "CPU"
        scene.cycles.samples = int(samples)
        if hasattr(scene.cycles, "use_denoising"):
            scene.cycles.use_denoising = False
        scene.render.resolution_x, scene.render.resolution_y = width, height
        scene.render.resolution_percentage = 100
        scene.view_settings.view_transform = "Standard"  # the ramp's colours as they are (no filmic tone map)
        scene.render.image_settings.file_format = "PNG"
        scene.render.image_settings.color_mode = "RGB"
        scene.render.filepath = str(tmp)
        scene.render.use_file_extension = False
        bpy.ops.render.render(write_still=True, scene=scene.name)
        if not Path(tmp).is_file() or Path(tmp).stat().st_size == 0:
            raise LadarError("the preview render wrote no image")
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
        bpy.data.scenes.remove(scene)
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(cam_data)
        bpy.data.worlds.remove(world)
    return path

"""A one-command preview render of result point clouds (Cycles, CPU) to a PNG, for reports.

The user's scene is not touched: a temporary scene links the point-cloud objects, gets its own camera and small
Cycles settings; it is rendered with ``bpy.ops.render.render(scene=...)`` and removed again (also on failure).

* **View.** The clouds of one flash or gated run are seen from the sensor itself: its pose (``metadata.json`` →
  ``sensor_pose``) and field of view, the image's aspect that of the receiver, and every point drawn as large as
  its pixel's footprint at the far end of the cloud (99th percentile of the ranges), so the picture fills like
  the range image it came from.  Other
  clouds (scanner, profiler, frame sequences, several runs) are framed: a camera looks at their bounding box
  from above-front-right with the whole box in view, points about 2.4 render pixels across (a few points, such
  as a profiler's echoes, larger: together 2 % of the picture, :func:`framed_point_px`).
* **Picture.** The film is transparent (the same on Blender 4.2 and 5.0, whose default world is grey); matplotlib
  then lays the render on a dark background with a title, the colour-ramp legend — the ramp's colours as
  rendered, the values at its ends and the unit (``ladar_color_label``) — and, in the sensor view, the angle
  axes in mrad of the range-image previews.

The PNG is written atomically (the raw render goes to a hidden temporary file, removed afterwards) and an
existing file is never replaced unless asked.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

from ..core.fileio.staging import new_temp_file
from .errors import LadarError
from .export import RESULT_TAG

PREVIEW_RESOLUTION = (640, 480)
PREVIEW_SAMPLES = 16
#: Viewing direction from the clouds' centre towards the camera (right, front, up in world axes).
VIEW_DIRECTION = (0.55, -0.65, 0.52)
CAMERA_ANGLE_RAD = math.radians(40.0)
BACKGROUND = "#101014"
#: Sensor view: point radius = this × half a receiver pixel's footprint at the far range: 1.5 (0.75 pixel) closes
#: the gap that round points leave between four pixel centres (0.71 pixel from each).
SENSOR_FILL = 1.5
#: Framed view: point radius in render pixels at the box's centre distance.
FRAMED_POINT_PX = 1.2
#: Framed view of a few points (a profiler's echoes): the points grow until together they would cover this
#: fraction of the picture, up to ``FRAMED_MAX_POINT_PX`` each (2 profiler echoes at 640 × 480: 31 px, where
#: 1.2 px left two specks); a cloud of more than about 1,400 points at 640 × 480 keeps ``FRAMED_POINT_PX``.
FRAMED_MIN_COVER = 0.02
FRAMED_MAX_POINT_PX = 32.0


def framed_point_px(n_points: int, width: int, height: int) -> float:
    """Point radius (render pixels) in the framed view: ``FRAMED_POINT_PX``, larger for a few points so that
    they cover ``FRAMED_MIN_COVER`` of the picture (π r² n = cover × width × height), at most
    ``FRAMED_MAX_POINT_PX``."""
    grow = math.sqrt(FRAMED_MIN_COVER * width * height / (math.pi * max(int(n_points), 1)))
    return min(FRAMED_MAX_POINT_PX, max(FRAMED_POINT_PX, grow))


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


def sensor_view(objects) -> dict | None:
    """The sensor's view of the run the objects came from — ``world_from_sensor`` (Blender units), field of view
    (rad), receiver pixels — when they are the clouds of one flash or gated run; else None (frame them)."""
    runs = {str(o.get(RESULT_TAG, "")) for o in objects}
    if len(runs) != 1:
        return None
    meta_path = Path(runs.pop()) / "metadata.json"
    if not meta_path.is_file():
        return None
    meta = json.loads(meta_path.read_text(encoding="utf-8"))
    pose = meta.get("sensor_pose")
    if meta.get("format") == "ladar-sequence" or meta.get("system_type") not in ("flash", "gated") or not pose:
        return None
    rx = meta["settings"]["receiver"]
    m = np.array(pose["world_from_sensor"], dtype=np.float64)
    rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    unit_scale = float(objects[0].get("ladar_unit_scale", 1.0))
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, m[:3, 3] / unit_scale
    return {"world_from_sensor": out, "fov_x_rad": float(rx["fov_x_rad"]), "fov_y_rad": float(rx["fov_y_rad"]),
            "width_px": int(rx["width_px"]), "unit_scale": unit_scale}


def legend_of(obj) -> dict:
    """The colour legend of a result cloud: label with unit, values at the ramp's ends, the ramp's colours as
    rendered (linear RGB → sRGB, the Standard view transform)."""
    from .colors import RAMP
    from .results import legend_ramp_node

    node = legend_ramp_node()
    stops = [(e.position, tuple(e.color)[:3]) for e in node.color_ramp.elements] if node is not None else list(RAMP)
    srgb = [(p, tuple(_linear_to_srgb(c) for c in rgb)) for p, rgb in stops]
    return {"label": str(obj.get("ladar_color_label", "")), "min": float(obj.get("ladar_color_min", 0.0)),
            "max": float(obj.get("ladar_color_max", 1.0)), "stops": srgb}


def _linear_to_srgb(c: float) -> float:
    c = min(max(float(c), 0.0), 1.0)
    return 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1 / 2.4) - 0.055


def compose(render_png: Path, out_png: Path, *, title: str, legend: dict, extent=None,
            overwrite: bool = False) -> None:
    """The render on a dark background with title, colour-ramp legend and (sensor view) angle axes (mrad)."""
    import matplotlib.image
    from matplotlib.colors import LinearSegmentedColormap, Normalize
    from matplotlib.cm import ScalarMappable

    from ..core.fileio.preview import new_figure, save_figure

    img = matplotlib.image.imread(str(render_png))
    h, w = img.shape[:2]
    fig = new_figure(7.4, max(3.0, min(9.0, 6.0 * h / w + 1.0)))
    fig.patch.set_facecolor(BACKGROUND)
    ax = fig.add_subplot()
    ax.set_facecolor(BACKGROUND)
    ax.imshow(img, extent=extent, interpolation="antialiased")
    fg = "#e8e8e8"
    if extent is None:
        ax.set_xticks([])
        ax.set_yticks([])
    else:
        ax.set_xlabel("horizontal angle (mrad)", color=fg)
        ax.set_ylabel("vertical angle (mrad)", color=fg)
        ax.tick_params(colors=fg)
    for spine in ax.spines.values():
        spine.set_color("#606060")
    ax.set_title(title, color=fg, fontsize=10)
    cmap = LinearSegmentedColormap.from_list("ladar_ramp", legend["stops"])
    lo, hi = legend["min"], legend["max"]
    bar = fig.colorbar(ScalarMappable(Normalize(lo, hi if hi > lo else lo + 1.0), cmap), ax=ax)
    bar.set_label(legend["label"], color=fg)
    bar.ax.tick_params(colors=fg)
    bar.outline.set_edgecolor("#606060")
    save_figure(fig, out_png, overwrite=overwrite)


def render_preview(objects, path, *, resolution=PREVIEW_RESOLUTION, samples: int = PREVIEW_SAMPLES,
                   overwrite: bool = False) -> Path:
    """Render ``objects`` (result point clouds) with Cycles on the CPU into the PNG ``path``; returns it.

    ``resolution``: the render's size (the sensor view keeps the width and takes the receiver's aspect); the
    PNG adds the title and legend around it."""
    from .colors import point_radius, set_point_radius

    objects = [o for o in objects if o is not None and o.type == "MESH" and len(o.data.vertices)]
    if not objects:
        raise LadarError("nothing to render: no result point cloud with points (simulate first, or select one)")
    path = Path(path)
    if path.exists() and not overwrite:
        raise LadarError(f"{path} exists: choose another file or allow replacing it")
    points = np.concatenate([_world_points(o) for o in objects])
    width, height = int(resolution[0]), int(resolution[1])
    view = sensor_view(objects)
    if view is not None:
        height = max(16, int(round(width * math.tan(0.5 * view["fov_y_rad"]) / math.tan(0.5 * view["fov_x_rad"]))))
    scene = bpy.data.scenes.new("Ladar Preview Render")
    cam_data = bpy.data.cameras.new("Ladar Preview Camera")
    cam = bpy.data.objects.new("Ladar Preview Camera", cam_data)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = new_temp_file(path.parent, f".{path.stem}.", ".png")
    os.close(fd)
    radii = []
    try:
        for obj in objects:
            scene.collection.objects.link(obj)
        scene.collection.objects.link(cam)
        if view is not None:
            m = view["world_from_sensor"]
            cam.matrix_world = Matrix(m.tolist())
            cam_data.sensor_fit = "HORIZONTAL"
            cam_data.angle = view["fov_x_rad"]
            ranges = np.linalg.norm(points - m[:3, 3], axis=1)
            near, far = float(ranges.min()), float(ranges.max())
            # sized for the farthest points: they just touch, nearer ones overlap (and hide what is behind them)
            footprint = float(np.percentile(ranges, 99)) * 2.0 * math.tan(0.5 * view["fov_x_rad"]) / view["width_px"]
            radius = 0.5 * SENSOR_FILL * footprint
            cam_data.clip_start = max(1e-3, 0.5 * near)
            cam_data.clip_end = 2.0 * far + 1.0
            hx, hy = 500.0 * view["fov_x_rad"], 500.0 * view["fov_y_rad"]
            extent = [-hx, hx, -hy, hy]
        else:
            cam_data.sensor_fit = "AUTO"
            cam_data.angle = CAMERA_ANGLE_RAD
            matrix, distance, radius_box = framing_camera(points, width / height)
            cam.matrix_world = matrix
            cam_data.clip_start = max(1e-3, 0.01 * (distance - radius_box))
            cam_data.clip_end = 2.0 * (distance + radius_box)
            radius = (framed_point_px(len(points), width, height)
                      * 2.0 * distance * math.tan(0.5 * CAMERA_ANGLE_RAD) / max(width, height))
            extent = None
        for obj in objects:  # the render's point size (restored afterwards)
            old_radius = point_radius(obj)
            if old_radius is not None:
                radii.append((obj, old_radius))
                set_point_radius([obj], radius)
        scene.camera = cam
        scene.render.film_transparent = True
        scene.render.engine = "CYCLES"
        scene.cycles.device = "CPU"
        scene.cycles.samples = int(samples)
        if hasattr(scene.cycles, "use_denoising"):
            scene.cycles.use_denoising = False
        scene.render.resolution_x, scene.render.resolution_y = width, height
        scene.render.resolution_percentage = 100
        scene.view_settings.view_transform = "Standard"  # the ramp's colours as they are (no filmic tone map)
        scene.render.image_settings.file_format = "PNG"
        scene.render.image_settings.color_mode = "RGBA"
        scene.render.filepath = str(tmp)
        scene.render.use_file_extension = False
        bpy.ops.render.render(write_still=True, scene=scene.name)
        if not Path(tmp).is_file() or Path(tmp).stat().st_size == 0:
            raise LadarError("the preview render wrote no image")
        legend = legend_of(objects[0])
        what = "sensor view" if view is not None else "framed"
        title = f"{objects[0].name if len(objects) == 1 else f'{len(objects)} point clouds'} ({what}): " \
                f"{len(points)} points, coloured by {legend['label'] or 'value'}"
        compose(Path(tmp), path, title=title, legend=legend, extent=extent, overwrite=overwrite)
    finally:
        for obj, old_radius in radii:
            set_point_radius([obj], old_radius)
        Path(tmp).unlink(missing_ok=True)
        bpy.data.scenes.remove(scene)
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(cam_data)
    return path

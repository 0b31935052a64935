"""Operators on results: import a run folder, show a waveform, render a preview of the point clouds."""
from pathlib import Path

import bpy
from bpy_extras.io_utils import ImportHelper

from ..core.errors import ConfigError
from ..ladar_addon.errors import LadarError
from ..ladar_addon.names import RESULT_TAG
from ..ladar_addon.blend_config import unit_scale
from ..ladar_addon.render import PREVIEW_RESOLUTION, PREVIEW_SAMPLES, render_preview
from ..ladar_addon.colors import result_objects
from ..ladar_addon.results import import_run, read_run_info
from ..ladar_addon.waveform_view import show_waveform

_USER_ERRORS = (ConfigError, LadarError, OSError)


def _run_of(context):
    """The run the user means: the active result object's run, else the scene's last run ("" if none)."""
    obj = getattr(context, "active_object", None)
    if obj is not None and obj.get(RESULT_TAG) is not None:
        return str(obj[RESULT_TAG])
    return context.scene.ladar.last_run


def _show_image(context, image):
    """Show ``image`` in the first Image Editor of the window, if there is one."""
    screen = getattr(context, "screen", None)
    for area in getattr(screen, "areas", ()):
        if area.type == "IMAGE_EDITOR":
            area.spaces.active.image = image
            area.tag_redraw()
            return True
    return False


class LADAR_OT_import_run(bpy.types.Operator, ImportHelper):
    """Import the point cloud(s) and images of an existing ladar run folder"""

    bl_idname = "ladar.import_run"
    bl_label = "Import Ladar Run"
    bl_options = {"REGISTER", "UNDO"}

    directory: bpy.props.StringProperty(subtype="DIR_PATH", options={"HIDDEN"})
    filter_glob: bpy.props.StringProperty(default="metadata.json", options={"HIDDEN"})

    def execute(self, context):
        scene = context.scene
        folder = Path(bpy.path.abspath(self.directory or Path(self.filepath).parent.as_posix()))
        props = scene.ladar
        try:
            objects, images = import_run(folder, scene, unit_scale=unit_scale(scene),
                                         replace=props.if_exists == "REPLACE", point_radius=props.point_radius,
                                         color_by=props.color_by, clouds=props.clouds)
        except _USER_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        props.last_run = str(folder)
        self.report({"INFO"}, f"Imported {len(objects)} point cloud(s) and {len(images)} image(s) from {folder}")
        return {"FINISHED"}


class LADAR_OT_waveform_view(bpy.types.Operator):
    """Plot the waveform of one pixel (or scanner pulse) of a run and show the plot as an image"""

    bl_idname = "ladar.waveform_view"
    bl_label = "Show Ladar Waveform"
    bl_options = {"REGISTER"}

    run: bpy.props.StringProperty(
        name="Run", subtype="DIR_PATH", default="",
        description="Run folder (empty: the active result object's run, else the scene's last run)")
    pixel_x: bpy.props.IntProperty(name="Pixel X", default=-1, min=-1,
                                   description="Receiver column (0 = left; -1: the strongest pixel's)")
    pixel_y: bpy.props.IntProperty(name="Pixel Y", default=-1, min=-1,
                                   description="Receiver row (0 = top; -1: the strongest pixel's)")
    pulse: bpy.props.IntProperty(
        name="Pulse", default=-1, min=-1,
        description="Scanner runs: pulse index (-1: the pulse with the most echoes, of those the strongest)")
    frame: bpy.props.IntProperty(
        name="Frame", default=-1, description="Frame of a sequence run (-1: the scene's current frame)")

    def invoke(self, context, event):
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        run = self.run or _run_of(context)
        if not run:
            self.report({"ERROR"}, "no run: simulate first, or select a result point cloud")
            return {"CANCELLED"}
        frame = context.scene.frame_current if self.frame < 0 else self.frame
        try:
            info = read_run_info(run)
            name = Path(run).name
            img, what = show_waveform(run, run_name=name, pixel_x=self.pixel_x, pixel_y=self.pixel_y,
                                      pulse=None if self.pulse < 0 else self.pulse,
                                      frame=frame if info.get("format") == "ladar-sequence" else None)
        except _USER_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _show_image(context, img)
        where = f"pulse {what['pulse']}" if "pulse" in what else f"pixel ({what['pixel_x']}, {what['pixel_y']})"
        echoes = len(what["echo_ranges_m"])
        self.report({"INFO"}, f"{what['view'].capitalize()} of {where}, {echoes} echo{'es' if echoes != 1 else ''}: "
                              f"image {img.name!r} ({img.filepath})")
        return {"FINISHED"}


class LADAR_OT_render_preview(bpy.types.Operator):
    """Render the result point clouds (selected ones, else those of the latest run) with Cycles on the CPU into \
a PNG for reports"""

    bl_idname = "ladar.render_preview"
    bl_label = "Render Ladar Preview"
    bl_options = {"REGISTER"}

    filepath: bpy.props.StringProperty(
        name="File", subtype="FILE_PATH", default="",
        description="PNG to write (empty: previews/render.png in the run folder; an existing file is kept and "
                    "a numbered name is used)")
    resolution_x: bpy.props.IntProperty(name="Width", default=PREVIEW_RESOLUTION[0], min=16, max=8192,
                                        subtype="PIXEL")
    resolution_y: bpy.props.IntProperty(name="Height", default=PREVIEW_RESOLUTION[1], min=16, max=8192,
                                        subtype="PIXEL")
    samples: bpy.props.IntProperty(name="Samples", default=PREVIEW_SAMPLES, min=1, max=4096)

    def execute(self, context):
        scene = context.scene
        selected = [o for o in getattr(context, "selected_objects", ()) if o.get(RESULT_TAG) is not None]
        objects = selected
        if not objects:
            last = scene.ladar.last_run
            objects = [o for o in result_objects(scene) if last and str(o[RESULT_TAG]).startswith(last)]
        if not objects:
            self.report({"ERROR"}, "no result point cloud: simulate first, or select one")
            return {"CANCELLED"}
        path = Path(bpy.path.abspath(self.filepath)) if self.filepath else \
            _free_name(Path(str(objects[0][RESULT_TAG])) / "previews" / "render.png")
        try:
            out = render_preview(objects, path, resolution=(self.resolution_x, self.resolution_y),
                                 samples=self.samples)
        except _USER_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        name = f"{objects[0].name}.render"
        old = bpy.data.images.get(name)
        if old is not None:
            bpy.data.images.remove(old)
        img = bpy.data.images.load(str(out), check_existing=False)
        img.name = name
        _show_image(context, img)
        self.report({"INFO"}, f"Rendered {len(objects)} point cloud(s) to {out}")
        return {"FINISHED"}


def _free_name(path: Path) -> Path:
    if not path.exists():
        return path
    k = 2
    while path.with_name(f"{path.stem}_{k}{path.suffix}").exists():
        k += 1
    return path.with_name(f"{path.stem}_{k}{path.suffix}")


CLASSES = (LADAR_OT_import_run, LADAR_OT_waveform_view, LADAR_OT_render_preview)

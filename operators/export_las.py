"""``bpy.ops.ladar.export_las``: a run's point cloud as a LAS 1.4 file (core.fileio.las.write_run_las)."""
from pathlib import Path

import bpy
from bpy_extras.io_utils import ExportHelper

from ..core.errors import ConfigError
from ..core.fileio.las import write_run_las
from ..ladar_addon.names import RESULT_TAG


def _run_of(obj):
    return obj.get(RESULT_TAG) if obj is not None else None


class LADAR_OT_export_las(bpy.types.Operator, ExportHelper):
    """Export a ladar run's point cloud as LAS 1.4 (point format 6: intensity, return number, number of returns,
    GPS time; simulated intensity and range as extra bytes)"""

    bl_idname = "ladar.export_las"
    bl_label = "Export Ladar LAS"

    filename_ext = ".las"
    filter_glob: bpy.props.StringProperty(default="*.las", options={"HIDDEN"})
    run_dir: bpy.props.StringProperty(
        name="Run Folder", subtype="DIR_PATH", default="",
        description="Run folder to export (empty: the run of the active ladar result object)")
    coordinates: bpy.props.EnumProperty(
        name="Coordinates", default="world",
        items=[("world", "World", "Blender world coordinates (m)"),
               ("sensor", "Sensor", "Sensor frame: −Z forward, +Y up, +X right (m)")],
        description="Coordinate frame of the exported points")
    overwrite: bpy.props.BoolProperty(name="Overwrite", default=False,
                                      description="Replace an existing LAS file of that name")

    def invoke(self, context, event):
        run = self.run_dir or _run_of(context.active_object)
        if run and not self.filepath:
            self.filepath = str(Path(run) / "points.las")
        return super().invoke(context, event)

    def execute(self, context):
        run = bpy.path.abspath(self.run_dir) if self.run_dir else _run_of(getattr(context, "active_object", None))
        if not run:
            self.report({"ERROR"}, "No run to export: select a ladar result object or set the Run Folder")
            return {"CANCELLED"}
        try:
            path = write_run_las(run, bpy.path.abspath(self.filepath), coordinates=self.coordinates,
                                 overwrite=self.overwrite)
        except (ConfigError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Wrote {path}")
        return {"FINISHED"}


CLASSES = (LADAR_OT_export_las,)


def menu_export(self, context):
    """File › Export › Ladar Point Cloud (.las)."""
    self.layout.operator(LADAR_OT_export_las.bl_idname, text="Ladar Point Cloud (.las)")


def register_menu():
    bpy.types.TOPBAR_MT_file_export.append(menu_export)


def unregister_menu():
    bpy.types.TOPBAR_MT_file_export.remove(menu_export)

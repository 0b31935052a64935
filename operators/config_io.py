"""``bpy.ops.ladar.export_config`` / ``bpy.ops.ladar.load_config``: the sensor's settings as a config file."""
import bpy
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..core.errors import ConfigError
from ..ladar_addon.cli import export_config
from ..ladar_addon.errors import LadarError
from ..ladar_addon.blend_config import apply_config_to_blender
from ..ladar_addon.run_inputs import active_sensor, build_config


class LADAR_OT_export_config(bpy.types.Operator, ExportHelper):
    """Write the active ladar sensor's settings to a JSON or TOML config file (for batch runs and sweeps)"""

    bl_idname = "ladar.export_config"
    bl_label = "Export Ladar Config"

    filename_ext = ".toml"
    filter_glob: bpy.props.StringProperty(default="*.toml;*.json", options={"HIDDEN"})

    def execute(self, context):
        try:
            # the file browser shows an existing file in red and the user confirms it: replace it
            path = export_config(context.scene, self.filepath, active_sensor(context.scene), overwrite=True)
        except (ConfigError, LadarError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Wrote {path}")
        return {"FINISHED"}


class LADAR_OT_load_config(bpy.types.Operator, ImportHelper):
    """Load a JSON or TOML config file into the active ladar sensor, the scene and the materials"""

    bl_idname = "ladar.load_config"
    bl_label = "Load Ladar Config"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: bpy.props.StringProperty(default="*.toml;*.json", options={"HIDDEN"})

    def execute(self, context):
        scene = context.scene
        try:
            sensor = active_sensor(scene)
            cfg, _ = build_config(scene, sensor, config_path=self.filepath)
            apply_config_to_blender(cfg, scene, sensor)
        except (ConfigError, LadarError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Loaded {self.filepath}")
        return {"FINISHED"}

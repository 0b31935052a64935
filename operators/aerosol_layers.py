"""``bpy.ops.ladar.aerosol_layers_clear``: remove the scene's range-layered aerosol (``atmosphere.aerosol_layers``,
set by a config file or preset; kept as JSON on the scene, ladar_addon/blend_config.py)."""
import bpy

from ..ladar_addon.blend_config import remove_tables


class LADAR_OT_aerosol_layers_clear(bpy.types.Operator):
    """Remove the aerosol layers: a homogeneous atmosphere again"""

    bl_idname = "ladar.aerosol_layers_clear"
    bl_label = "Clear Aerosol Layers"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        remove_tables(context.scene, "atmosphere", ("aerosol_layers",))
        return {"FINISHED"}


CLASSES = (LADAR_OT_aerosol_layers_clear,)

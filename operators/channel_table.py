"""``bpy.ops.ladar.channel_table_load`` / ``ladar.channel_table_clear``: the rotating head's channel table from a
CSV file (ladar_addon/channel_tables.py)."""
import bpy
from bpy_extras.io_utils import ImportHelper

from ..core.errors import ConfigError
from ..ladar_addon.channel_tables import clear_channel_table, set_channel_table_file


def _camera_poll(context) -> bool:
    obj = context.object
    return obj is not None and obj.type == "CAMERA"


class LADAR_OT_channel_table_load(bpy.types.Operator, ImportHelper):
    """Use a CSV file (elevation_deg, azimuth_offset_deg, fire_offset_s per channel) as the rotating head's
    channel table; a bad file is refused with its row and column, and nothing changes"""

    bl_idname = "ladar.channel_table_load"
    bl_label = "Load Channel Table"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: bpy.props.StringProperty(default="*.csv;*.txt", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return _camera_poll(context)

    def execute(self, context):
        try:
            n = set_channel_table_file(context.object, bpy.path.abspath(self.filepath))
        except ConfigError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Channel table: {n} channels from {self.filepath}")
        return {"FINISHED"}


class LADAR_OT_channel_table_clear(bpy.types.Operator):
    """Remove the channel table: evenly spaced channels again"""

    bl_idname = "ladar.channel_table_clear"
    bl_label = "Clear Channel Table"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _camera_poll(context)

    def execute(self, context):
        clear_channel_table(context.object)
        return {"FINISHED"}


CLASSES = (LADAR_OT_channel_table_load, LADAR_OT_channel_table_clear)

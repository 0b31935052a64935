"""Operators: thin wrappers around ``ladar_addon`` functions."""
import bpy

from .config_io import LADAR_OT_export_config, LADAR_OT_load_config
from .simulate import LADAR_OT_simulate

CLASSES = (LADAR_OT_simulate, LADAR_OT_export_config, LADAR_OT_load_config)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)

"""Blender presets for the atmosphere and the detector (Blender's preset system).

Shipped presets live in the extension's ``presets/ladar_simulator/<kind>/`` folder (registered with
``bpy.utils.register_preset_path``, read-only); presets a user adds with the "+" button go to
``<user scripts>/presets/ladar_simulator/<kind>/``.  A preset is a Python file that sets the same properties
the panels draw (``Scene.ladar_atmosphere.*``, ``Object.ladar.detector.*``), in their *stored* units (see
``ladar_addon.properties``: Cn² and dark currents are stored scaled, distances in Blender units).
"""
from __future__ import annotations

import os

import bpy
from bl_operators.presets import AddPresetBase

from .properties import ATMOSPHERE_FIELDS, SENSOR_FIELDS

#: The extension root (holds ``presets/``).
EXTENSION_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ATMOSPHERE_SUBDIR = "ladar_simulator/atmosphere"
DETECTOR_SUBDIR = "ladar_simulator/detector"


def shipped_preset_dir(subdir: str) -> str:
    return os.path.join(EXTENSION_ROOT, "presets", *subdir.split("/"))


class LADAR_MT_atmosphere_presets(bpy.types.Menu):
    bl_label = "Atmosphere Presets"
    preset_subdir = ATMOSPHERE_SUBDIR
    preset_operator = "script.execute_preset"
    preset_add_operator = "ladar.atmosphere_preset_add"
    draw = bpy.types.Menu.draw_preset


class LADAR_MT_detector_presets(bpy.types.Menu):
    bl_label = "Detector Presets"
    preset_subdir = DETECTOR_SUBDIR
    preset_operator = "script.execute_preset"
    preset_add_operator = "ladar.detector_preset_add"
    draw = bpy.types.Menu.draw_preset


class LADAR_OT_atmosphere_preset_add(AddPresetBase, bpy.types.Operator):
    """Add or remove a ladar atmosphere preset (all atmosphere settings of the scene)"""
    bl_idname = "ladar.atmosphere_preset_add"
    bl_label = "Add Atmosphere Preset"
    preset_menu = "LADAR_MT_atmosphere_presets"
    preset_subdir = ATMOSPHERE_SUBDIR
    preset_defines = ["atmosphere = bpy.context.scene.ladar_atmosphere"]

    preset_values = [f"atmosphere.{f.attr}" for f in ATMOSPHERE_FIELDS]


#: The sensor a detector preset applies to: the camera shown in the Properties editor, else the scene's ladar
#: sensor or camera (same expression as in the shipped preset files).
SENSOR_EXPRESSION = ("obj = bpy.context.object if getattr(bpy.context, \"object\", None) is not None and "
                     "bpy.context.object.type == \"CAMERA\" else "
                     "(bpy.context.scene.ladar.sensor or bpy.context.scene.camera)")


class LADAR_OT_detector_preset_add(AddPresetBase, bpy.types.Operator):
    """Add or remove a ladar detector preset (all detector settings of the sensor)"""
    bl_idname = "ladar.detector_preset_add"
    bl_label = "Add Detector Preset"
    preset_menu = "LADAR_MT_detector_presets"
    preset_subdir = DETECTOR_SUBDIR
    preset_defines = [SENSOR_EXPRESSION, "detector = obj.ladar.detector"]

    preset_values = [f"detector.{f.attr}" for f in SENSOR_FIELDS["detector"]]


def draw_preset_header(layout, menu_cls, add_operator: str):
    """Preset menu plus add/remove buttons, for a panel's ``draw_header_preset``."""
    row = layout.row(align=True)
    row.menu(menu_cls.__name__, text=menu_cls.bl_label)
    row.operator(add_operator, text="", icon="ADD")
    op = row.operator(add_operator, text="", icon="REMOVE")
    op.remove_active = True


CLASSES = (LADAR_MT_atmosphere_presets, LADAR_MT_detector_presets, LADAR_OT_atmosphere_preset_add,
           LADAR_OT_detector_preset_add)


def register():
    bpy.utils.register_preset_path(EXTENSION_ROOT)
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
    bpy.utils.unregister_preset_path(EXTENSION_ROOT)

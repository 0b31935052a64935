"""Blender presets for the atmosphere, the detector, whole sensors and material BRDFs (Blender's preset system).

Shipped presets live in the extension's ``presets/ladar_simulator/<kind>/`` folder (registered with
``bpy.utils.register_preset_path``, read-only); presets a user adds with the "+" button go to
``<user scripts>/presets/ladar_simulator/<kind>/``.  A preset is a Python file that sets the same properties
the panels draw (``Scene.ladar_atmosphere.*``, ``Object.ladar.<group>.*``, ``Material.ladar_brdf.*``), in their
*stored* units (see ``ladar_addon.properties``: wavelengths in nm, Cn² and dark currents stored scaled,
distances in Blender units).

* ``sensor``: a whole sensor — system type, laser, receiver, range gate, scanner, gated viewing, detection and
  detector settings, and the camera's lens (which sets the receiver's field of view); the run settings (seed,
  threads, memory) are left alone.
* ``material``: a material's ladar BRDF (model, parameters, measured table rows), enabled.
"""
from __future__ import annotations

import os

import bpy
from bl_operators.presets import AddPresetBase

from .properties import ATMOSPHERE_FIELDS, BRDF_FIELDS, SENSOR_FIELDS

#: The extension root (holds ``presets/``).
EXTENSION_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ATMOSPHERE_SUBDIR = "ladar_simulator/atmosphere"
DETECTOR_SUBDIR = "ladar_simulator/detector"
SENSOR_SUBDIR = "ladar_simulator/sensor"
MATERIAL_SUBDIR = "ladar_simulator/material"
#: Sensor groups a whole-sensor preset stores (not "run": seed, threads and memory are not the sensor's).
SENSOR_PRESET_GROUPS = tuple(g for g in SENSOR_FIELDS if g != "run")
#: Camera settings a sensor preset stores: with the receiver's pixel counts they give its field of view.
SENSOR_PRESET_CAMERA = ("sensor_fit", "sensor_width", "sensor_height", "lens")


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


class LADAR_MT_sensor_presets(bpy.types.Menu):
    bl_label = "Sensor Presets"
    preset_subdir = SENSOR_SUBDIR
    preset_operator = "script.execute_preset"
    preset_add_operator = "ladar.sensor_preset_add"
    draw = bpy.types.Menu.draw_preset


class LADAR_OT_sensor_preset_add(AddPresetBase, bpy.types.Operator):
    """Add or remove a whole-sensor ladar preset (system type, laser, receiver, gate, scanner, gated viewing,
    detection, detector and the camera lens)"""
    bl_idname = "ladar.sensor_preset_add"
    bl_label = "Add Sensor Preset"
    preset_menu = "LADAR_MT_sensor_presets"
    preset_subdir = SENSOR_SUBDIR
    preset_defines = [SENSOR_EXPRESSION, "ladar = obj.ladar", "cam = obj.data"]

    preset_values = (["ladar.system_type"] + [f"ladar.{g}" for g in SENSOR_PRESET_GROUPS]
                     + [f"cam.{a}" for a in SENSOR_PRESET_CAMERA])


class LADAR_MT_material_presets(bpy.types.Menu):
    bl_label = "Material Presets"
    preset_subdir = MATERIAL_SUBDIR
    preset_operator = "script.execute_preset"
    preset_add_operator = "ladar.material_preset_add"
    draw = bpy.types.Menu.draw_preset


class LADAR_OT_material_preset_add(AddPresetBase, bpy.types.Operator):
    """Add or remove a ladar material preset (the material's BRDF model, parameters and measured table)"""
    bl_idname = "ladar.material_preset_add"
    bl_label = "Add Material Preset"
    preset_menu = "LADAR_MT_material_presets"
    preset_subdir = MATERIAL_SUBDIR
    preset_defines = ["brdf = bpy.context.material.ladar_brdf"]

    preset_values = (["brdf.enabled"] + [f"brdf.{f.attr}" for f in BRDF_FIELDS]
                     + ["brdf.table", "brdf.table_source", "brdf.origin"])


CLASSES = (LADAR_MT_atmosphere_presets, LADAR_MT_detector_presets, LADAR_OT_atmosphere_preset_add,
           LADAR_OT_detector_preset_add, LADAR_MT_sensor_presets, LADAR_OT_sensor_preset_add,
           LADAR_MT_material_presets, LADAR_OT_material_preset_add)


def register():
    bpy.utils.register_preset_path(EXTENSION_ROOT)
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
    bpy.utils.unregister_preset_path(EXTENSION_ROOT)

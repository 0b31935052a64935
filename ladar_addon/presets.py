"""Blender presets for the atmosphere, the detector, whole sensors and material BRDFs (Blender's preset system).

Shipped presets live in the extension's ``presets/ladar_simulator/<kind>/`` folder (registered with
``bpy.utils.register_preset_path``, read-only); presets a user adds with the "+" button go to
``<user scripts>/presets/ladar_simulator/<kind>/``.  A preset is a Python file that sets the same properties
the panels draw (``Scene.ladar_atmosphere.*``, ``Object.ladar.<group>.*``, ``Material.ladar_brdf.*``), in their
*stored* units (see ``ladar_addon.properties``: panel units such as ns, µJ, nm and ×1e-14 m^-2/3, distances in
Blender units).

* ``sensor``: a whole sensor — system type, laser, receiver, range gate, scanner, gated viewing, detection and
  detector settings, and the camera's lens (which sets the receiver's field of view); the run settings (seed,
  threads, memory) are left alone.
* ``material``: a material's ladar BRDF (model, parameters, measured table rows), enabled.
"""
from __future__ import annotations

import os

import bpy
from bl_operators.presets import AddPresetBase

from .fields import ATMOSPHERE_FIELDS, BRDF_FIELDS, SENSOR_FIELDS, SYSTEM_TYPE_FIELD, write_value

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
    """Add or remove a ladar atmosphere preset (the atmosphere panel's fields; not the aerosol layers)"""
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


# ------------------------------------------------------------------------------------------------------------
# Shipped sensor and material presets: values in core (SI) units, converted and validated here
# ------------------------------------------------------------------------------------------------------------
def preset_sensor(context=None):
    """The camera a sensor preset applies to (the same rule as :data:`SENSOR_EXPRESSION`)."""
    context = context or bpy.context
    obj = getattr(context, "object", None)
    if obj is not None and obj.type == "CAMERA":
        return obj
    scene = context.scene
    return scene.ladar.sensor or scene.camera


def sensor_preset_config(settings: dict, scene, obj):
    """The validated core config a sensor preset gives ``obj``: its current settings with ``settings``
    (``{"system_type": ..., "<group>": {field: SI value}}``; ``receiver.fov_x_rad`` sets the camera angle, the
    vertical field of view following from the square pixels) applied."""
    import math

    from ..core.config.settings import GROUPS
    from ..core.config.files import config_from_dict, config_to_dict
    from ..core.errors import ConfigError
    from .blend_config import config_from_blender

    unknown = [k for k in settings if k != "system_type" and k not in GROUPS]
    if unknown:
        raise ConfigError(f"preset.{unknown[0]}", settings[unknown[0]], "system_type or a settings group: "
                          + ", ".join(GROUPS))
    from ..core.config.settings import SCANNER_TABLE_FIELDS

    data = config_to_dict(config_from_blender(scene, obj))
    if "scanner" in settings:  # a preset's scanner replaces the tables (channel table, Risley) it does not name
        for key in SCANNER_TABLE_FIELDS:
            data["scanner"].pop(key, None)
    for key, value in settings.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    rx = data["receiver"]
    if "fov_x_rad" in settings.get("receiver", {}):
        rx["fov_y_rad"] = 2.0 * math.atan(math.tan(0.5 * rx["fov_x_rad"]) * rx["height_px"] / rx["width_px"])
    return config_from_dict(data)


def apply_sensor_preset(settings: dict, context=None):
    """Apply a whole-sensor preset given in SI units (shipped preset files call this).  Only the settings named
    change; everything is validated before anything changes.  Returns the sensor object."""
    from .errors import LadarError
    from .blend_config import check_sensor, unit_scale
    from .sensor import set_camera_receiver_fov

    context = context or bpy.context
    obj = preset_sensor(context)
    if obj is None:
        raise LadarError("no camera to apply the sensor preset to: select a camera or set Scene > Ladar > Sensor")
    check_sensor(obj)
    scene = context.scene
    cfg = sensor_preset_config(settings, scene, obj)
    scale = unit_scale(scene)
    fields = {g: {f.name: f for f in maps} for g, maps in SENSOR_FIELDS.items()}
    for f in (SYSTEM_TYPE_FIELD,):
        if f.name in settings:
            setattr(obj.ladar, f.attr, f.to_blender(getattr(cfg, f.name)))
    for group, values in settings.items():
        if group == "system_type":
            continue
        props = getattr(obj.ladar, group)
        for name in values:
            f = fields[group].get(name)
            if f is not None:
                write_value(props, f, getattr(getattr(cfg, group), name), scale)
    if "scanner" in settings:
        from .blend_config import write_tables
        write_tables(obj, "scanner", cfg.scanner)
    rx = cfg.receiver
    if "fov_x_rad" in settings.get("receiver", {}):
        set_camera_receiver_fov(obj.data, rx.fov_x_rad, rx.fov_y_rad, rx.width_px, rx.height_px)
    return obj


def apply_named_sensor_preset(name: str, context=None):
    """Apply a real-sensor preset of the core registry (``core/presets/sensors/<name>.toml``, core.presets) the
    way :func:`apply_sensor_preset` applies a shipped one: its settings (not its ``[published]`` figures),
    validated before anything changes.  The generated menu files (scripts/sensor_table.py) call this."""
    from ..core.presets import preset_settings

    return apply_sensor_preset(preset_settings(name), context)


def apply_material_preset(settings: dict, origin: str, context=None):
    """Apply a material BRDF preset given in SI units (``BRDFSettings`` fields; a table as
    ``table_angle_deg``/``table_brdf_per_sr`` lists) to the context's material, enabled, with ``origin`` shown
    in the panel.  Validated before anything changes.  A preset without a table keeps the material's table."""
    from ..core.config.settings import BRDFSettings
    from ..core.config.validate import validate
    from .blend_config import read_table, write_table

    material = getattr(context or bpy.context, "material", None)
    if material is None:
        from .errors import LadarError
        raise LadarError("no material to apply the material preset to: select an object with a material")
    current = {f.name: f.to_core(getattr(material.ladar_brdf, f.attr)) for f in BRDF_FIELDS}
    current.update(read_table(material.ladar_brdf))
    brdf = BRDFSettings(**{**current, **settings})
    validate(brdf, f"materials.{material.name}.")
    props = material.ladar_brdf
    for f in BRDF_FIELDS:
        setattr(props, f.attr, f.to_blender(getattr(brdf, f.name)))
    if "table_angle_deg" in settings:
        write_table(props, brdf.table_angle_deg, brdf.table_brdf_per_sr)
        props.table_source = "preset"
    props.origin = origin
    props.enabled = True
    return material


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

"""Blender properties generated 1:1 from the core settings dataclasses, and the mapping between the two.

Where the settings live in a .blend:

==========================================  ==============================================================
core ``SimulationConfig``                   Blender
==========================================  ==============================================================
``system_type`` and every group but         ``Object.ladar.<group>`` (used on camera objects: the sensor)
``atmosphere`` (``laser``, ``receiver``,
``gate``, ``detection``, ``run``, and any
group the core adds)
``receiver.fov_x_rad``, ``fov_y_rad``       derived from the camera (``ladar_addon.sensor``), not stored
``run.seed``                                ``Scene.ladar.seed``
``atmosphere``                              ``Scene.ladar_atmosphere``
``materials[name]``                         ``Material.ladar_brdf`` of every material with ``enabled`` on
                                            (a measured table as rows: ``ladar_addon.materials``)
==========================================  ==============================================================

Every other plain setting of the core becomes a property with its label (the schema's ``label``: "Pulse
Width (FWHM)"), default, range (``lo``/``hi``), description (doc + unit) and Blender subtype (guarded against
subtypes an older Blender lacks); enum items carry the schema's ``choice_labels`` ("PIN photodiode").
Where a Blender property cannot hold the SI value as is, the stored value is scaled, and the mapping
(:class:`FieldMap`) converts both ways:

* a setting with a *panel unit* (``core.config.settings.PANEL_UNITS``) is stored and shown in it, with the unit
  in the label: times in ns (``pulse_fwhm_ns``, ``gate_start_ns``, ...), energies in µJ or fJ, the beam
  divergence in mrad, wavelengths in nm, extinction in 1/km, the scanner's pulse rate in kHz, Cn² in
  ×1e-14 m^-2/3, dark currents in pA and nA (Blender's unit system prints "0 s" for a nanosecond); a property
  whose stored unit changed got a new name, and a .blend holding the old one is migrated on load
  (:func:`ladar_addon.blend_config.migrate_legacy_units`);
* ``DISTANCE`` settings are stored in Blender units (metres / ``scene.unit_settings.scale_length``);
* byte counts above the 32-bit range of an ``IntProperty`` (``run.max_memory_bytes``) are stored in whole
  MiB (``max_memory_mib``; a config value that is not a whole number of MiB is rounded);
* ``run.seed`` is limited to 0 … 2³¹−1 in a .blend (larger seeds: ``--seed`` or a config file).

Scripts set settings in SI through :func:`set_settings` (``{"atmosphere.cn2_m_23": 5e-15}``), never by
writing an SI value into a scaled property.

Blender stores floats in single precision; :func:`config_from_blender` returns the shortest decimal that
rounds to the stored float32 (scaled from the panel unit), so a value typed as 1e-3 comes back as exactly 1e-3;
a renamed setting keeps the exact SI value set through the API beside it (:func:`ladar_addon.fields.write_value`).
"""
from __future__ import annotations

import bpy

from ..core.config.settings import BRDFSettings
from .fields import (ATMOSPHERE_FIELDS, BRDF_FIELDS, INT32_MAX, MIB, SCENE_GROUPS, SEED_FIELD, SENSOR_FIELDS,
                     SENSOR_GROUPS, TOP_FIELDS, FieldMap)
from .moved import moved_names


def _number_subtypes() -> set:
    """Property subtypes this Blender knows (4.2 lacks some of the newer ones)."""
    return set(bpy.types.FloatProperty.bl_rna.properties["subtype"].enum_items.keys())


_SUBTYPES = _number_subtypes()


def _subtype(f: FieldMap) -> str:
    return f.subtype if f.subtype in _SUBTYPES else "NONE"


def blender_property(f: FieldMap):
    """The bpy property that stores the setting ``f`` (its range, default, unit label and description)."""
    name = f.label
    # Show the unit in the label where Blender shows none (no unit subtype: a panel unit such as ns, or MiB).
    if f.kind in ("float", "int") and _subtype(f) == "NONE" and f.unit_text():
        name += f" ({f.unit_text()})"
    desc = f.description()
    lo, hi = f.meta.get("lo"), f.meta.get("hi")
    if f.kind == "enum":
        items = [(c, f.choice_label(c), f"{f.meta.get('doc', '')}: {c}") for c in f.meta["choices"]]
        return bpy.props.EnumProperty(name=name, description=desc, items=items, default=f.default)
    if f.kind == "bool":
        return bpy.props.BoolProperty(name=name, description=desc, default=bool(f.default))
    if f.kind == "int":
        if f.conversion == "mib":
            lo = None if lo is None else max(1, lo // MIB)
            hi = None if hi is None else hi // MIB
        kwargs = {"min": max(lo, -INT32_MAX - 1) if lo is not None else -INT32_MAX - 1,
                  "max": min(hi, INT32_MAX) if hi is not None else INT32_MAX}
        subtype = _subtype(f) if _subtype(f) in ("NONE", "PIXEL", "UNSIGNED", "PERCENTAGE", "FACTOR",
                                                   "ANGLE", "TIME", "DISTANCE") else "NONE"
        return bpy.props.IntProperty(name=name, description=desc, subtype=subtype,
                                     default=f.to_blender(f.default), **kwargs)
    kwargs = {}
    if f.conversion == "distance":
        kwargs = distance_limits_bu(lo, hi)
    else:
        if lo is not None:
            kwargs["min"] = f.to_blender(lo)
        if hi is not None:
            kwargs["max"] = f.to_blender(hi)
    default = f.to_blender(f.default)
    hi_b = kwargs.get("max")
    magnitude = abs(default) if default else (abs(hi_b) if hi_b is not None else 1.0)
    # Small unit-less values (k_eff 0.02, ...): six decimals; values in a panel unit read 1 … 1e6 or so: three.
    precision = 6 if _subtype(f) == "NONE" and magnitude <= 1.0 and not f.meta.get("panel_unit") else 3
    return bpy.props.FloatProperty(name=name, description=desc, subtype=_subtype(f), default=default,
                                   precision=precision, **kwargs)


#: Metres per Blender unit that Blender allows (``UnitSettings.scale_length`` hard range).
_SCALE_RNA = bpy.types.UnitSettings.bl_rna.properties["scale_length"]
SCALE_LENGTH_RANGE = (float(_SCALE_RNA.hard_min), float(_SCALE_RNA.hard_max))


def distance_limits_bu(lo_m, hi_m) -> dict:
    """``min``/``max``/``soft_min``/``soft_max`` of a distance property stored in Blender units.

    A property's range is fixed when it is registered, but Blender units are metres / ``scale_length`` of
    whichever scene: the hard range covers ``[lo_m, hi_m]`` at every unit scale Blender allows (so no value the
    core accepts is ever clipped on the way into a .blend), the soft range (slider drag) is the SI range read at
    1 m per unit.  Values outside the SI range are reported by the core's validation, in metres.
    """
    s_min, s_max = SCALE_LENGTH_RANGE
    limits = {}
    if lo_m is not None:
        limits["min"] = lo_m / s_max if lo_m >= 0 else lo_m / s_min
        limits["soft_min"] = lo_m
    if hi_m is not None:
        limits["max"] = hi_m / s_min if hi_m >= 0 else hi_m / s_max
        limits["soft_max"] = hi_m
    return limits


class LadarBRDFTableRow(bpy.types.PropertyGroup):
    """One row of a measured monostatic BRDF table"""

    angle_deg: bpy.props.FloatProperty(
        name="Angle (deg)", min=0.0, max=90.0, precision=3,
        description="Incidence angle θ between the surface normal and the (monostatic) laser direction, in "
                    "degrees")
    brdf_per_sr: bpy.props.FloatProperty(
        name="BRDF (1/sr)", min=0.0, precision=6,
        description="Measured monostatic BRDF f_r at this angle [1/sr]")


#: Extra properties of ``LadarBRDFSettings`` besides the generated scalar settings.
def extra_brdf_properties() -> dict:
    return {
        "table": bpy.props.CollectionProperty(
            type=LadarBRDFTableRow, name="BRDF Table",
            description="Measured monostatic BRDF table (model 'table'): incidence angle (deg) vs f_r (1/sr)"),
        "table_source": bpy.props.StringProperty(
            name="Table Source", default="",
            description="File the measured BRDF table was imported from (the table itself is stored in the "
                        ".blend)"),
        "origin": bpy.props.StringProperty(
            name="Origin", default="",
            description="Where these BRDF values came from (a preset, the Principled BSDF mapping, ...)"),
        "plot": bpy.props.PointerProperty(
            type=bpy.types.Image, name="BRDF Plot",
            description="Plot of this material's BRDF vs incidence angle (packed into the .blend)"),
    }


# ------------------------------------------------------------------------------------------------------------
# PropertyGroups
# ------------------------------------------------------------------------------------------------------------
def _make_group(class_name: str, fields: list[FieldMap], doc: str, extra: dict | None = None):
    annotations = dict(extra or {})
    annotations.update({f.attr: blender_property(f) for f in fields})
    return type(class_name, (bpy.types.PropertyGroup,), {"__annotations__": annotations, "__doc__": doc,
                                                         "__module__": __name__})


def _group_class_name(group: str) -> str:
    return "Ladar" + "".join(w.capitalize() for w in group.split("_")) + "Settings"


#: One PropertyGroup per sensor group: LadarLaserSettings, LadarReceiverSettings, LadarGateSettings, ...
_GROUP_CLASSES = {g: _make_group(_group_class_name(g), SENSOR_FIELDS[g], cls.__doc__)
                  for g, cls in SENSOR_GROUPS.items()}
LadarLaserSettings = _GROUP_CLASSES["laser"]
LadarReceiverSettings = _GROUP_CLASSES["receiver"]
LadarGateSettings = _GROUP_CLASSES["gate"]
LadarDetectionSettings = _GROUP_CLASSES["detection"]
LadarRunSettings = _GROUP_CLASSES["run"]
LadarAtmosphereSettings = _make_group("LadarAtmosphereSettings", ATMOSPHERE_FIELDS,
                                      SCENE_GROUPS["atmosphere"].__doc__)
LadarBRDFSettings = _make_group(
    "LadarBRDFSettings", BRDF_FIELDS, BRDFSettings.__doc__,
    {"enabled": bpy.props.BoolProperty(
        name="Ladar BRDF", default=False,
        description="Use these ladar BRDF settings for this material (off: the simulator's default grey "
                    "Lambertian, 30 %)"), **extra_brdf_properties()})

def _sensor_annotations():
    ann = {f.attr: blender_property(f) for f in TOP_FIELDS}
    for group, cls in _GROUP_CLASSES.items():
        ann[group] = bpy.props.PointerProperty(type=cls, name=group.replace("_", " ").title())
    return ann


LadarSensorSettings = type("LadarSensorSettings", (bpy.types.PropertyGroup,), {
    "__annotations__": _sensor_annotations(), "__module__": __name__,
    "__doc__": "Ladar sensor settings of a camera object (system type, laser, receiver, gate, detection, run)"})


#: Blender ≥ 4.5 warns about "//" paths unless the property says it supports them (4.2 lacks the option).
_BLEND_RELATIVE_PATH = ({"PATH_SUPPORTS_BLEND_RELATIVE"}
                        if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties else set())


def _poll_camera(self, obj):
    return obj.type == "CAMERA"


def _update_color_by(props, context):
    from .colors import recolor, result_objects
    recolor(result_objects(context.scene), props.color_by)


def _update_point_radius(props, context):
    from .colors import result_objects, set_point_radius
    set_point_radius(result_objects(context.scene), props.point_radius)


class LadarSceneSettings(bpy.types.PropertyGroup):
    """Scene-wide ladar settings: which camera is the sensor, where runs go, the run seed."""

    sensor: bpy.props.PointerProperty(
        type=bpy.types.Object, name="Sensor", poll=_poll_camera,
        description="Camera object simulated as the ladar sensor (empty: the scene camera)")
    output_dir: bpy.props.StringProperty(
        name="Output Folder", subtype="DIR_PATH", default="//ladar_runs", options=_BLEND_RELATIVE_PATH,
        description="Folder that receives one run folder per simulated frame (// = next to the .blend file)")
    seed: blender_property(SEED_FIELD)
    if_exists: bpy.props.EnumProperty(
        name="If Exists", default="STOP", items=[
            ("STOP", "Stop", "Refuse to run when the run folder or result objects of that name exist"),
            ("REPLACE", "Replace", "Replace the run folder and the result objects and images of the same name"),
            ("NEW", "New Name", "Keep what exists: the run gets the next free name (<name>_2, <name>_3, ...)")],
        description="What a run does when its run folder or result objects already exist (never duplicated "
                    "silently)")
    use_frame_range: bpy.props.BoolProperty(
        name="Frame Range", default=False,
        description="Simulate the scene's frame range (start, end, step) into one sequence run folder instead "
                    "of the current frame")
    clouds: bpy.props.EnumProperty(
        name="Point Clouds", default="RUN", items=[
            ("RUN", "One per Run", "A frame range gives one point cloud of all frames (attribute frame)"),
            ("FRAME", "One per Frame", "A frame range gives one point cloud per frame, in a collection")],
        description="How the points of a frame range come into the scene")
    write_previews: bpy.props.BoolProperty(
        name="PNG Previews", default=True,
        description="Write a false-colour PNG beside every EXR image of a run (and the profiler's waveform plot)")
    color_by: bpy.props.EnumProperty(
        name="Colour By", default="INTENSITY", update=_update_color_by,
        items=[("INTENSITY", "Intensity", "Echo peak amplitude, 0 … its 99th percentile"),
               ("RANGE", "Range", "Range from the sensor, minimum … maximum"),
               ("ECHO", "Echo Number", "1 = first echo of its pixel or pulse"),
               ("SNR", "Detection SNR", "Signal-to-noise ratio of the detection (noisy receiver only)"),
               ("FRAME", "Frame", "Scene frame of the point (frame sequences)"),
               ("CHANNEL", "Channel", "Scanner channel (rotating multi-channel scanner)")],
        description="Point attribute that colours the result point clouds through the colour ramp")
    point_radius: bpy.props.FloatProperty(
        name="Point Radius", subtype="DISTANCE", default=0.05, min=0.0, soft_max=1.0,
        update=_update_point_radius,
        description="Display radius of the points of imported point clouds (all result clouds of the scene)")
    last_run: bpy.props.StringProperty(
        name="Last Run", subtype="DIR_PATH", default="",
        description="Run folder of the latest simulation (waveform view and preview render use it by default)")
    reference_range_m: bpy.props.FloatProperty(
        name="Reference Range", subtype="DISTANCE", default=1000.0, min=1e-3, soft_max=1e5,
        description="Range of the read-only figures in the panels (transmission, turbulence, SNR); not used "
                    "by the simulation")
    import_results: bpy.props.BoolProperty(
        name="Import Results", default=True,
        description="Bring the point cloud and the range/intensity images into the .blend after a run")


CLASSES = (*_GROUP_CLASSES.values(), LadarSensorSettings, LadarAtmosphereSettings, LadarBRDFTableRow,
           LadarBRDFSettings,
           LadarSceneSettings)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.ladar = bpy.props.PointerProperty(type=LadarSensorSettings, name="Ladar Sensor")
    bpy.types.Scene.ladar = bpy.props.PointerProperty(type=LadarSceneSettings, name="Ladar")
    bpy.types.Scene.ladar_atmosphere = bpy.props.PointerProperty(type=LadarAtmosphereSettings,
                                                                 name="Ladar Atmosphere")
    bpy.types.Material.ladar_brdf = bpy.props.PointerProperty(type=LadarBRDFSettings, name="Ladar BRDF")
    from . import blend_config
    blend_config.register()


def unregister():
    from . import blend_config
    blend_config.unregister()
    del bpy.types.Material.ladar_brdf
    del bpy.types.Scene.ladar_atmosphere
    del bpy.types.Scene.ladar
    del bpy.types.Object.ladar
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)


def property_group_class(group: str):
    """The PropertyGroup class holding a core settings group ("laser", ..., "atmosphere", "brdf")."""
    if group == "atmosphere":
        return LadarAtmosphereSettings
    if group == "brdf":
        return LadarBRDFSettings
    return _GROUP_CLASSES[group]


def sensor_field_maps(group: str) -> list[FieldMap]:
    """Field maps of a sensor group (for panels and tests)."""
    return SENSOR_FIELDS[group]


#: Names that lived here before the Blender <-> core conversion and the field maps got their own modules.
_MOVED = {"blend_config": ("unit_scale", "material_key", "brdf_from_material", "check_sensor", "config_from_blender",
                           "find_material", "apply_config_to_blender", "set_settings"),
          "fields": ("SYSTEM_TYPE_FIELD", "all_core_paths")}


__getattr__ = moved_names(__name__, _MOVED)

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

Every other plain setting of the core becomes a property of the same name, with its default, range (``lo``/
``hi``), description (doc + unit) and Blender subtype (guarded against subtypes an older Blender lacks).
Where a Blender property cannot hold the SI value as is, the stored value is scaled, and the mapping
(:class:`FieldMap`) converts both ways:

* ``WAVELENGTH`` settings are stored in nanometres (Blender's wavelength unit);
* tiny settings without a Blender unit (largest allowed value < 1e-3, e.g. Cn², or a default < 1e-4, e.g. a
  dark current of 1e-12 A) are stored in units of a power of ten (label "×1e-14 m^-2/3"), so the panel shows
  their digits;
* ``DISTANCE`` settings are stored in Blender units (metres / ``scene.unit_settings.scale_length``);
* byte counts above the 32-bit range of an ``IntProperty`` (``run.max_memory_bytes``) are stored in whole
  MiB (``max_memory_mib``; a config value that is not a whole number of MiB is rounded);
* ``run.seed`` is limited to 0 … 2³¹−1 in a .blend (larger seeds: ``--seed`` or a config file).

Scripts set settings in SI through :func:`set_settings` (``{"atmosphere.cn2_m_23": 5e-15}``), never by
writing an SI value into a scaled property.

Blender stores floats in single precision; :func:`config_from_blender` returns the shortest decimal that
rounds to the stored float32, so a value typed as 1e-3 comes back as exactly 1e-3.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal

import bpy
import numpy as np

from ..core.config.settings import (DEFAULT_BRDF, GROUPS, BRDFSettings, RunSettings, SimulationConfig,
                                    config_from_dict, config_to_dict, field_specs, validate)
from ..core.errors import ConfigError
from .errors import LadarError
from .materials import LadarBRDFTableRow, extra_brdf_properties, read_table, write_table
from .sensor import camera_receiver_fov_rad, set_camera_receiver_fov

INT32_MAX = 2**31 - 1
MIB = 2**20

_CORE_GROUPS = {g: type(getattr(SimulationConfig(), g)) for g in GROUPS}
#: Settings groups stored on the scene (``Scene.ladar_<group>``); every other core group is a sensor setting.
SCENE_GROUPS = {"atmosphere": _CORE_GROUPS["atmosphere"]}
#: Settings groups stored on the sensor object (``Object.ladar.<group>``): laser, receiver, gate, detection, run
#: and any group the core adds later.
SENSOR_GROUPS = {g: cls for g, cls in _CORE_GROUPS.items() if g not in SCENE_GROUPS}
#: Settings not stored as sensor properties (derived from the camera, or kept on the scene).
NOT_ON_SENSOR = {("receiver", "fov_x_rad"), ("receiver", "fov_y_rad"), ("run", "seed")}
#: Receiver size of a new sensor (the core default may differ).
SENSOR_DEFAULT_OVERRIDES = {("receiver", "width_px"): 64, ("receiver", "height_px"): 64}

#: Name suffixes that spell a field's unit (stripped from the label; the unit shows through the subtype or
#: in parentheses).  Keyed by the unit, so "specular_a" (no unit) keeps its "A".
_UNIT_SUFFIXES = {"m": "_m", "s": "_s", "J": "_j", "rad": "_rad", "px": "_px", "B": "_bytes", "1/m": "_per_m",
                  "1/s": "_per_s", "A": "_a", "e-": "_e", "m^-2/3": "_m_23"}
_ACRONYMS = {"Fwhm": "FWHM", "Fov": "FOV", "Brdf": "BRDF", "Cn2": "Cn²", "Apd": "APD", "Adc": "ADC",
             "Dof": "DOF"}


def _number_subtypes() -> set:
    """Property subtypes this Blender knows (4.2 lacks some of the newer ones)."""
    return set(bpy.types.FloatProperty.bl_rna.properties["subtype"].enum_items.keys())


_SUBTYPES = _number_subtypes()


def _label(name: str, unit: str = "") -> str:
    suffix = _UNIT_SUFFIXES.get(unit)
    if suffix and name.endswith(suffix) and len(name) > len(suffix):
        name = name[: -len(suffix)]
    words = [w.capitalize() for w in name.split("_")]
    return " ".join(_ACRONYMS.get(w, w) for w in words)


def _shortest_float32(value: float) -> str:
    """The shortest decimal string that rounds to the same float32 as ``value``."""
    return str(np.float32(value))


@dataclass(frozen=True)
class FieldMap:
    """How one core setting maps onto one Blender property."""

    group: str | None      # core group ("laser", ...), None for top-level settings, "brdf" for BRDFSettings
    name: str              # core field name
    attr: str              # Blender property name
    kind: str              # "float", "int", "bool" or "enum"
    default: object        # core default (SI)
    meta: dict
    conversion: str = ""   # "", "nm", "pow10", "distance" or "mib"
    exponent: int = 0      # "nm": −9; "pow10": Blender stores the value in units of 10^exponent

    @property
    def path(self) -> str:
        return self.name if self.group in (None, "brdf") else f"{self.group}.{self.name}"

    @property
    def subtype(self) -> str:
        wanted = self.meta.get("subtype") or "NONE"
        return wanted if wanted in _SUBTYPES else "NONE"

    def unit_text(self) -> str:
        if self.conversion == "nm":
            return "nm"
        if self.conversion == "pow10":
            unit = self.meta.get("unit") or ""
            return f"×1e{self.exponent} {unit}".rstrip()
        if self.conversion == "mib":
            return "MiB"
        if self.conversion == "distance":
            return "Blender units = m / unit scale"
        return self.meta.get("unit") or ""

    # -- conversions ------------------------------------------------------------------------------------------
    def to_blender(self, value, unit_scale: float = 1.0):
        if self.kind == "float":
            value = float(value)
            if self.conversion in ("nm", "pow10"):
                return float(Decimal(repr(value)).scaleb(-self.exponent))
            if self.conversion == "distance":
                return value / unit_scale
            return value
        if self.kind == "int" and self.conversion == "mib":
            return max(1, int(round(value / MIB)))
        if self.kind == "int":
            hi = self.meta.get("hi")
            if value > INT32_MAX:
                raise ConfigError(self.path, value, f"at most {INT32_MAX} when stored in a .blend"
                                  + (f" (the simulator accepts up to {hi} from a config file)" if hi else ""))
            return int(value)
        return value

    def to_core(self, value, unit_scale: float = 1.0):
        if self.kind == "float":
            text = _shortest_float32(value)
            if self.conversion in ("nm", "pow10"):
                return float(Decimal(text).scaleb(self.exponent))
            if self.conversion == "distance":
                return float(text) * unit_scale
            v, lo, hi = float(text), self.meta.get("lo"), self.meta.get("hi")
            # A bound float32 cannot hold (2π) is stored rounded outwards: it reads back as the bound itself.
            if hi is not None and v > hi and np.float32(hi) == np.float32(value):
                return float(hi)
            if lo is not None and v < lo and np.float32(lo) == np.float32(value):
                return float(lo)
            return v
        if self.kind == "int" and self.conversion == "mib":
            return int(value) * MIB
        if self.kind == "int":
            return int(value)
        if self.kind == "bool":
            return bool(value)
        return str(value)

    # -- the Blender property ---------------------------------------------------------------------------------
    def description(self) -> str:
        doc = self.meta.get("doc", "")
        unit = self.unit_text()
        text = doc + (f" [{unit}]" if unit else "")
        path = f"materials.<name>.{self.name}" if self.group == "brdf" else self.path
        return f"{text}. Config: {path}"

    def property(self):
        name = _label(self.name, self.meta.get("unit") or "")
        # Show the unit in the label where Blender shows none (no unit subtype, or a scaled storage unit).
        if self.conversion in ("mib", "pow10") or (self.subtype == "NONE" and self.kind in ("float", "int")
                                                   and (self.meta.get("unit") or self.conversion == "nm")):
            name += f" ({self.unit_text()})"
        desc = self.description()
        lo, hi = self.meta.get("lo"), self.meta.get("hi")
        if self.kind == "enum":
            items = [(c, c.replace("_", " ").title(), f"{self.meta.get('doc', '')}: {c}")
                     for c in self.meta["choices"]]
            return bpy.props.EnumProperty(name=name, description=desc, items=items, default=self.default)
        if self.kind == "bool":
            return bpy.props.BoolProperty(name=name, description=desc, default=bool(self.default))
        if self.kind == "int":
            if self.conversion == "mib":
                lo = None if lo is None else max(1, lo // MIB)
                hi = None if hi is None else hi // MIB
            kwargs = {"min": max(lo, -INT32_MAX - 1) if lo is not None else -INT32_MAX - 1,
                      "max": min(hi, INT32_MAX) if hi is not None else INT32_MAX}
            subtype = self.subtype if self.subtype in ("NONE", "PIXEL", "UNSIGNED", "PERCENTAGE", "FACTOR",
                                                       "ANGLE", "TIME", "DISTANCE") else "NONE"
            return bpy.props.IntProperty(name=name, description=desc, subtype=subtype,
                                         default=self.to_blender(self.default), **kwargs)
        kwargs = {}
        if self.conversion == "distance":
            kwargs = distance_limits_bu(lo, hi)
        else:
            if lo is not None:
                kwargs["min"] = self.to_blender(lo)
            if hi is not None:
                kwargs["max"] = self.to_blender(hi)
        default = self.to_blender(self.default)
        hi_b = kwargs.get("max")
        magnitude = abs(default) if default else (abs(hi_b) if hi_b is not None else 1.0)
        # Small SI values (J, 1/m, ...) have no unit display in Blender: show six decimals for them.
        precision = 6 if self.subtype == "NONE" and magnitude <= 1.0 else 3
        return bpy.props.FloatProperty(name=name, description=desc, subtype=self.subtype, default=default,
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


def _field_map(group, name, default, meta) -> FieldMap:
    if meta.get("choices"):
        kind = "enum"
    elif isinstance(default, bool):
        kind = "bool"
    elif isinstance(default, int):
        kind = "int"
    elif isinstance(default, float):
        kind = "float"
    else:  # pragma: no cover - the core declares only these
        raise TypeError(f"setting {group}.{name} has an unsupported type {type(default).__name__}")
    default = SENSOR_DEFAULT_OVERRIDES.get((group, name), default)
    conversion, attr, exponent = "", name, 0
    hi = meta.get("hi")
    if kind == "float" and meta.get("subtype") == "WAVELENGTH":
        conversion, exponent = "nm", -9
    elif kind == "float" and (meta.get("subtype") or "NONE") == "NONE" and hi is not None and 0 < hi < 1e-3:
        # Values far below what a six-decimal field shows (Cn² ~ 1e-14): store them in units of 10^exponent,
        # so the largest allowed value shows as 1000.
        conversion, exponent = "pow10", int(math.floor(math.log10(hi))) - 3
    elif kind == "float" and (meta.get("subtype") or "NONE") == "NONE" and 0 < abs(default) < 1e-4:
        # A tiny default (dark current ~ 1e-12 A): the default shows as 1 in units of 10^exponent.
        conversion, exponent = "pow10", int(math.floor(math.log10(abs(default))))
    elif kind == "float" and meta.get("subtype") == "DISTANCE":
        conversion = "distance"
    elif kind == "int" and meta.get("unit") == "B" and (meta.get("hi") or 0) > INT32_MAX:
        conversion, attr = "mib", name.removesuffix("_bytes") + "_mib"
    return FieldMap(group, name, attr, kind, default, meta, conversion, exponent)


def group_field_maps(group: str, cls, skip=()) -> list[FieldMap]:
    return [_field_map(group, n, d, m) for n, d, m in field_specs(cls) if (group, n) not in skip]


#: Field maps of every Blender-stored setting, by group.
SENSOR_FIELDS = {g: group_field_maps(g, cls, NOT_ON_SENSOR) for g, cls in SENSOR_GROUPS.items()}
#: Top-level plain settings (``system_type``), stored on ``Object.ladar``.
TOP_FIELDS = group_field_maps(None, SimulationConfig)
SYSTEM_TYPE_FIELD = next(f for f in TOP_FIELDS if f.name == "system_type")
ATMOSPHERE_FIELDS = group_field_maps("atmosphere", SCENE_GROUPS["atmosphere"])
BRDF_FIELDS = group_field_maps("brdf", BRDFSettings)
SEED_FIELD = next(_field_map("run", n, d, m) for n, d, m in field_specs(RunSettings) if n == "seed")


# ------------------------------------------------------------------------------------------------------------
# PropertyGroups
# ------------------------------------------------------------------------------------------------------------
def _make_group(class_name: str, fields: list[FieldMap], doc: str, extra: dict | None = None):
    annotations = dict(extra or {})
    annotations.update({f.attr: f.property() for f in fields})
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
    ann = {f.attr: f.property() for f in TOP_FIELDS}
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
    from .results import recolor, result_objects
    recolor(result_objects(context.scene), props.color_by)


def _update_point_radius(props, context):
    from .results import result_objects, set_point_radius
    set_point_radius(result_objects(context.scene), props.point_radius)


class LadarSceneSettings(bpy.types.PropertyGroup):
    """Scene-wide ladar settings: which camera is the sensor, where runs go, the run seed."""

    sensor: bpy.props.PointerProperty(
        type=bpy.types.Object, name="Sensor", poll=_poll_camera,
        description="Camera object simulated as the ladar sensor (empty: the scene camera)")
    output_dir: bpy.props.StringProperty(
        name="Output Folder", subtype="DIR_PATH", default="//ladar_runs", options=_BLEND_RELATIVE_PATH,
        description="Folder that receives one run folder per simulated frame (// = next to the .blend file)")
    seed: SEED_FIELD.property()
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


def unregister():
    del bpy.types.Material.ladar_brdf
    del bpy.types.Scene.ladar_atmosphere
    del bpy.types.Scene.ladar
    del bpy.types.Object.ladar
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)


# ------------------------------------------------------------------------------------------------------------
# Blender <-> core
# ------------------------------------------------------------------------------------------------------------
def unit_scale(scene) -> float:
    """Metres per Blender unit (``scale_length``; 1 when the scene uses no unit system)."""
    us = scene.unit_settings
    return 1.0 if us.system == "NONE" else float(us.scale_length)


def material_key(material) -> str:
    """The name under which a material's BRDF appears in ``SimulationConfig.materials`` and the scene."""
    return material.name_full


def brdf_from_material(material) -> BRDFSettings:
    """The material's ladar BRDF, or the core default when it has none enabled (or ``material`` is None)."""
    if material is None:
        return DEFAULT_BRDF
    props = material.ladar_brdf
    if not props.enabled:
        return DEFAULT_BRDF
    return BRDFSettings(**{f.name: f.to_core(getattr(props, f.attr)) for f in BRDF_FIELDS}, **read_table(props))


def _read_group(props, fields, unit_scale_m):
    return {f.name: f.to_core(getattr(props, f.attr), unit_scale_m) for f in fields}


def _write_group(props, fields, settings, unit_scale_m):
    for f in fields:
        setattr(props, f.attr, f.to_blender(getattr(settings, f.name), unit_scale_m))


def check_sensor(sensor_obj) -> None:
    if sensor_obj is None:
        raise LadarError("no ladar sensor: set Scene > Ladar > Sensor or the scene camera to a camera object")
    if sensor_obj.type != "CAMERA":
        raise LadarError(f"the ladar sensor {sensor_obj.name!r} is a {sensor_obj.type.lower()} object, "
                         f"not a camera")


def config_from_blender(scene, sensor_obj) -> SimulationConfig:
    """The core settings stored in ``scene`` and on ``sensor_obj`` (a camera object).  Not validated.

    The receiver field of view comes from the camera (:func:`ladar_addon.sensor.camera_receiver_fov_rad`);
    ``materials`` lists the BRDF of every material with ladar BRDF settings enabled.
    """
    check_sensor(sensor_obj)
    scale = unit_scale(scene)
    sensor = sensor_obj.ladar
    groups = {g: _read_group(getattr(sensor, g), SENSOR_FIELDS[g], scale) for g in SENSOR_GROUPS}
    groups["run"]["seed"] = SEED_FIELD.to_core(scene.ladar.seed)
    rx = groups["receiver"]
    rx["fov_x_rad"], rx["fov_y_rad"] = camera_receiver_fov_rad(sensor_obj.data, rx["width_px"], rx["height_px"])
    kwargs = {g: cls(**groups[g]) for g, cls in SENSOR_GROUPS.items()}
    kwargs["atmosphere"] = SCENE_GROUPS["atmosphere"](**_read_group(scene.ladar_atmosphere, ATMOSPHERE_FIELDS,
                                                                    scale))
    kwargs.update({f.name: f.to_core(getattr(sensor, f.attr)) for f in TOP_FIELDS})
    kwargs["materials"] = {material_key(m): brdf_from_material(m) for m in bpy.data.materials
                           if m.ladar_brdf.enabled}
    return SimulationConfig(**kwargs)


def find_material(key: str):
    for m in bpy.data.materials:
        if material_key(m) == key:
            return m
    return None


def apply_config_to_blender(cfg: SimulationConfig, scene, sensor_obj) -> None:
    """Store ``cfg`` in ``scene`` and on ``sensor_obj``: the inverse of :func:`config_from_blender`.

    The config is validated first (nothing changes if it is invalid).  The camera lens is set so that the
    camera gives ``cfg.receiver``'s field of view.  ``cfg.materials`` must name materials of the .blend; they
    get their ladar BRDF enabled and set, every other material's ladar BRDF is disabled.
    """
    check_sensor(sensor_obj)
    validate(cfg)
    rx = cfg.receiver
    scale = unit_scale(scene)
    missing = [name for name in cfg.materials if find_material(name) is None]
    if missing:
        raise ConfigError(f"materials.{missing[0]}", missing[0], "the name of a material in the .blend file: "
                          + ", ".join(material_key(m) for m in bpy.data.materials))
    # Check everything that can fail before changing anything.
    SEED_FIELD.to_blender(cfg.run.seed)
    for group in SENSOR_GROUPS:
        for f in SENSOR_FIELDS[group]:
            f.to_blender(getattr(getattr(cfg, group), f.name), scale)
    cam = sensor_obj.data
    saved_lens = cam.lens
    set_camera_receiver_fov(cam, rx.fov_x_rad, rx.fov_y_rad, rx.width_px, rx.height_px)
    try:
        sensor = sensor_obj.ladar
        for f in TOP_FIELDS:
            setattr(sensor, f.attr, f.to_blender(getattr(cfg, f.name), scale))
        for group in SENSOR_GROUPS:
            _write_group(getattr(sensor, group), SENSOR_FIELDS[group], getattr(cfg, group), scale)
        scene.ladar.seed = SEED_FIELD.to_blender(cfg.run.seed)
        _write_group(scene.ladar_atmosphere, ATMOSPHERE_FIELDS, cfg.atmosphere, scale)
        for m in bpy.data.materials:
            brdf = cfg.materials.get(material_key(m))
            if brdf is None:
                m.ladar_brdf.enabled = False
            else:
                _write_group(m.ladar_brdf, BRDF_FIELDS, brdf, 1.0)
                write_table(m.ladar_brdf, brdf.table_angle_deg, brdf.table_brdf_per_sr)
                m.ladar_brdf.enabled = True
    except Exception:
        cam.lens = saved_lens
        raise


def set_settings(scene, sensor_obj, values: dict) -> SimulationConfig:
    """Set settings by their config path, in SI units: the Python API for scripts.

    Several properties store a scaled value (wavelengths in nm, Cn² and dark currents in units of a power of
    ten, distances in Blender units, memory in MiB: :class:`FieldMap`), so writing an SI value straight into
    them is wrong by that scale (``scene.ladar_atmosphere.cn2_m_23 = 5e-15`` stores 5e-29 m^-2/3).  This sets
    ``{"atmosphere.cn2_m_23": 5e-15, "laser.wavelength_m": 532e-9, ...}`` as the simulator will read them.
    Paths: ``system_type``, ``<group>.<field>`` (``run.seed`` too; ``receiver.fov_x_rad``/``fov_y_rad`` set
    the camera lens) and ``materials.<material name>.<field>`` (a material with its ladar BRDF enabled).
    Everything is validated before anything changes (ConfigError naming the path).  Returns the config now
    stored."""
    data = config_to_dict(config_from_blender(scene, sensor_obj))
    for path, value in values.items():
        if path == "system_type":
            data[path] = value
            continue
        head, _, rest = path.partition(".")
        if head == "materials":
            name, _, field = rest.rpartition(".")
            if name not in data["materials"]:
                raise ConfigError(path, value, "materials.<name>.<field> of a material with its ladar BRDF enabled: "
                                  + (", ".join(data["materials"]) or "none is"))
            target = data["materials"][name]
        elif head in GROUPS:
            field, target = rest, data[head]
        else:
            raise ConfigError(path, value, "system_type, <group>.<field> (groups: " + ", ".join(GROUPS)
                              + ") or materials.<name>.<field>")
        if field not in target:
            raise ConfigError(path, value, f"a setting of {head}: " + ", ".join(target))
        target[field] = value
    cfg = config_from_dict(data)
    apply_config_to_blender(cfg, scene, sensor_obj)
    return cfg


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


def all_core_paths() -> set:
    """Dotted paths of every core setting that has a home in Blender (for the 1:1 test)."""
    paths = {f.path for f in TOP_FIELDS} | {SEED_FIELD.path, "receiver.fov_x_rad", "receiver.fov_y_rad"}
    for fields in SENSOR_FIELDS.values():
        paths |= {f.path for f in fields}
    paths |= {f.path for f in ATMOSPHERE_FIELDS}
    return paths



"""Blender ↔ core settings: a SimulationConfig read from a scene, its sensor camera and its materials, and
written back (the inverse), through the field maps of :mod:`.fields`.  The PropertyGroups themselves are in
:mod:`.properties`."""
from __future__ import annotations

import json

import bpy

from ..core.config.settings import DEFAULT_BRDF, GROUPS, BRDFSettings, SimulationConfig, table_fields
from ..core.config.validate import validate
from ..core.config.files import config_from_dict, config_to_dict
from ..core.errors import ConfigError
from .errors import LadarError
from .fields import (ATMOSPHERE_FIELDS, BRDF_FIELDS, CORE_GROUPS, SCENE_GROUPS, SEED_FIELD, SENSOR_FIELDS, SENSOR_GROUPS,
                     TOP_FIELDS, migrate_group, read_value, shortest_float32, write_value)
from .sensor import camera_receiver_fov_rad, set_camera_receiver_fov


def table_float(value: float) -> float:
    """A BRDF table value as stored (float32) read back as the shortest decimal that rounds to it."""
    return float(shortest_float32(value))


def read_table(props) -> dict:
    """The stored table as core lists: ``{"table_angle_deg": [...], "table_brdf_per_sr": [...]}``."""
    return {"table_angle_deg": [table_float(r.angle_deg) for r in props.table],
            "table_brdf_per_sr": [table_float(r.brdf_per_sr) for r in props.table]}


def write_table(props, angle_deg, brdf_per_sr) -> None:
    """Replace the stored table (lengths must match; validate first)."""
    if len(angle_deg) != len(brdf_per_sr):
        raise ConfigError("table_brdf_per_sr", f"{len(brdf_per_sr)} values",
                          f"one BRDF value per angle ({len(angle_deg)} angles)")
    props.table.clear()
    for angle, value in zip(angle_deg, brdf_per_sr):
        row = props.table.add()
        row.angle_deg = float(angle)
        row.brdf_per_sr = float(value)


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


def read_group(props, fields, unit_scale_m):
    return {f.name: read_value(props, f, unit_scale_m) for f in fields}


def write_group(props, fields, settings, unit_scale_m):
    for f in fields:
        write_value(props, f, getattr(settings, f.name), unit_scale_m)


def migrate_legacy_units() -> int:
    """Properties of every ladar sensor (camera object) and scene of the open file whose stored unit changed
    (issue 27: ``pulse_fwhm_s`` in seconds became ``pulse_fwhm_ns``) get the value a file saved before the
    change holds (:func:`ladar_addon.fields.migrate_group`); run on every file load.  Returns how many were
    set."""
    n = 0
    for obj in bpy.data.objects:
        if obj.type != "CAMERA" or obj.library is not None:
            continue
        for group in SENSOR_GROUPS:
            n += migrate_group(getattr(obj.ladar, group), SENSOR_FIELDS[group])
    for scene in bpy.data.scenes:
        if scene.library is None:
            n += migrate_group(scene.ladar_atmosphere, ATMOSPHERE_FIELDS)
    return n


@bpy.app.handlers.persistent
def _migrate_on_load(*_args):
    migrate_legacy_units()


def register():
    if _migrate_on_load not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_migrate_on_load)


def unregister():
    if _migrate_on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_migrate_on_load)


def check_sensor(sensor_obj) -> None:
    if sensor_obj is None:
        raise LadarError("no ladar sensor: set Scene > Ladar > Sensor or the scene camera to a camera object")
    if sensor_obj.type != "CAMERA":
        raise LadarError(f"the ladar sensor {sensor_obj.name!r} is a {sensor_obj.type.lower()} object, "
                         f"not a camera")


#: The settings of a group that have no Blender property (:func:`core.config.settings.table_fields`: the scanner's
#: channel table, its file and the Risley prisms and emitters; the atmosphere's aerosol layers) are kept as JSON in a
#: custom property ``ladar_<group>_tables`` of the ID that holds the group's Blender properties: the sensor camera
#: object for a sensor group, the scene for the atmosphere (absent: defaults).  Only values that differ from the
#: defaults are stored.
def tables_key(group: str) -> str:
    return f"ladar_{group}_tables"


#: The scanner's key (the name .blend files saved before the atmosphere had tables already use).
SCANNER_TABLES_KEY = tables_key("scanner")


def tables_owner(group: str, scene, sensor_obj):
    """The ID whose custom property holds ``group``'s tables: the scene for a scene group, else the sensor."""
    return scene if group in SCENE_GROUPS else sensor_obj


def _table_fields(group: str) -> tuple[str, ...]:
    return table_fields(CORE_GROUPS[group])


def read_tables(owner, group: str) -> dict:
    """The table settings of ``group`` stored on ``owner`` (only those that differ from the defaults).  A custom
    property that is not a JSON object of the group's table fields (edited by hand) raises a ConfigError naming
    it."""
    key = tables_key(group)
    text = owner.get(key, "")
    if not text:
        return {}
    where = f"{owner.name}[{key!r}]"
    allowed = "a JSON object of " + (", ".join(_table_fields(group)) or "no settings")
    try:
        values = json.loads(text) if isinstance(text, str) else None
    except ValueError:
        values = None
    if not isinstance(values, dict):
        raise ConfigError(where, str(text)[:80], allowed)
    unknown = [k for k in values if k not in _table_fields(group)]
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}", values[unknown[0]], allowed)
    return values


def store_tables(owner, group: str, values: dict) -> None:
    """Store ``values`` (table settings of ``group``) on ``owner``; the custom property removed when empty."""
    key = tables_key(group)
    if values:
        owner[key] = json.dumps(values)
    elif key in owner:
        del owner[key]


def remove_tables(owner, group: str, names) -> None:
    """Back to the defaults for the table settings ``names`` of ``group`` on ``owner`` (the others kept)."""
    tables = read_tables(owner, group)
    for name in names:
        tables.pop(name, None)
    store_tables(owner, group, tables)


def write_tables(owner, group: str, settings) -> None:
    """Store the table settings of ``settings`` (a core settings group) that differ from the defaults."""
    default = CORE_GROUPS[group]()
    store_tables(owner, group, {k: getattr(settings, k) for k in _table_fields(group)
                                if getattr(settings, k) != getattr(default, k)})


def config_from_blender(scene, sensor_obj) -> SimulationConfig:
    """The core settings stored in ``scene`` and on ``sensor_obj`` (a camera object).  Not validated.

    The receiver field of view comes from the camera (:func:`ladar_addon.sensor.camera_receiver_fov_rad`);
    ``materials`` lists the BRDF of every material with ladar BRDF settings enabled.
    """
    check_sensor(sensor_obj)
    scale = unit_scale(scene)
    sensor = sensor_obj.ladar
    groups = {g: read_group(getattr(sensor, g), SENSOR_FIELDS[g], scale) for g in SENSOR_GROUPS}
    groups["run"]["seed"] = SEED_FIELD.to_core(scene.ladar.seed)
    for g in SENSOR_GROUPS:
        groups[g].update(read_tables(sensor_obj, g))
    rx = groups["receiver"]
    rx["fov_x_rad"], rx["fov_y_rad"] = camera_receiver_fov_rad(sensor_obj.data, rx["width_px"], rx["height_px"])
    kwargs = {g: cls(**groups[g]) for g, cls in SENSOR_GROUPS.items()}
    kwargs["atmosphere"] = SCENE_GROUPS["atmosphere"](**read_group(scene.ladar_atmosphere, ATMOSPHERE_FIELDS,
                                                                    scale), **read_tables(scene, "atmosphere"))
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
            write_group(getattr(sensor, group), SENSOR_FIELDS[group], getattr(cfg, group), scale)
        for g in GROUPS:
            write_tables(tables_owner(g, scene, sensor_obj), g, getattr(cfg, g))
        scene.ladar.seed = SEED_FIELD.to_blender(cfg.run.seed)
        write_group(scene.ladar_atmosphere, ATMOSPHERE_FIELDS, cfg.atmosphere, scale)
        for m in bpy.data.materials:
            brdf = cfg.materials.get(material_key(m))
            if brdf is None:
                m.ladar_brdf.enabled = False
            else:
                write_group(m.ladar_brdf, BRDF_FIELDS, brdf, 1.0)
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

"""Ladar sensor panel in the Object Data tab of cameras, with one sub-panel per settings group.

The system type chooses what shows (``ladar_addon.sensor.SYSTEM_GROUPS``/``field_used``): the scanner settings
only for "scanner", the gated-viewing settings only for "gated", the range gate and echo detection not for
"gated", the receiver's pixel counts not for "scanner"/"profiler", the scan-pattern settings by pattern.
"""
import math

import bpy

from ..core.constants import SPEED_OF_LIGHT_M_S
from ..ladar_addon.presets import LADAR_MT_detector_presets, LADAR_MT_sensor_presets, draw_preset_header
from ..ladar_addon.channel_tables import channel_table_lines
from ..ladar_addon.fields import SENSOR_FIELDS, TOP_FIELDS, read_value
from ..ladar_addon.sensor import camera_receiver_fov_rad, field_used, group_used
from .common import (atmosphere_settings, draw_lines, reference_range_m, sensor_config, simulate_button,
                     simulate_options)


def si_values(props, group) -> dict:
    """The SI values of a sensor group's settings (the panels store them in panel units: ns, µJ, ...)."""
    return {f.name: read_value(props, f) for f in SENSOR_FIELDS[group] if f.conversion != "distance"}


def _readable(props, f) -> str:
    """``FieldMap.readable`` of the field's value ("" if it cannot be read: draw must never fail)."""
    try:
        return f.readable(read_value(props, f))
    except Exception:  # noqa: BLE001
        return ""


def draw_group_fields(layout, props, group, system_type, skip=(), scan_pattern=None):
    """One row per setting of ``group`` that ``system_type`` uses (labels, units and ranges come from the
    property definitions)."""
    for f in SENSOR_FIELDS[group]:
        if f.attr not in skip and f.name not in skip and field_used(system_type, group, f.name, scan_pattern):
            layout.prop(props, f.attr)
            readable = _readable(props, f)  # "= 100 mJ" under a µJ field holding 100000
            if readable:
                row = layout.row()
                row.alignment = "RIGHT"
                row.label(text=f"= {readable}")


class _SensorPanel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "data"

    @classmethod
    def poll(cls, context):
        obj = context.object
        return obj is not None and obj.type == "CAMERA" and context.camera is not None


def _system_lines(obj, cfg) -> list[str]:
    """What the camera and the system settings make of the sensor (read-only)."""
    kind = obj.ladar.system_type
    rx = obj.ladar.receiver
    if kind == "scanner":
        if cfg is None:
            return ["Scan figures unavailable: invalid sensor settings"]
        from ..core.config.derived import n_scan_pulses, scan_duration_s
        sc = cfg.scanner
        return [f"Scan: {sc.pattern}, {n_scan_pulses(cfg)} pulses in {scan_duration_s(cfg):.4g} s "
                f"({sc.pulse_rate_hz:.4g} Hz)", "The camera gives the pose only (its angle is not used)"]
    w, h = (1, 1) if kind == "profiler" else (rx.width_px, rx.height_px)
    fov_x, fov_y = camera_receiver_fov_rad(obj.data, w, h)
    lines = [f"Field of view {math.degrees(fov_x):.4g}° × {math.degrees(fov_y):.4g}° (from the camera)"]
    if kind == "profiler":
        lines.append("One detector element over the whole field of view")
    elif kind == "gated":
        g = si_values(obj.ladar.gated, "gated")
        first = 0.5 * SPEED_OF_LIGHT_M_S * g["first_delay_s"]
        last = first + 0.5 * SPEED_OF_LIGHT_M_S * g["delay_step_s"] * (g["n_slices"] - 1)
        lines.append(f"{g['n_slices']} slices, gates opening at {first:.5g} … {last:.5g} m")
    return lines


class LADAR_PT_sensor(_SensorPanel, bpy.types.Panel):
    bl_label = "Ladar Sensor"
    bl_idname = "LADAR_PT_sensor"

    def draw_header_preset(self, context):
        draw_preset_header(self.layout, LADAR_MT_sensor_presets, "ladar.sensor_preset_add")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        obj = context.object
        for f in TOP_FIELDS:
            layout.prop(obj.ladar, f.attr)
        try:
            lines = _system_lines(obj, sensor_config(context.scene, obj))
            icon = "CAMERA_DATA"
        except Exception as exc:  # noqa: BLE001 - draw must never fail (e.g. an orthographic camera)
            lines, icon = [str(exc)], "ERROR"
        col = layout.column(align=True)
        for i, text in enumerate(lines):
            col.label(text=text, icon=icon if i == 0 else "BLANK1")
        scene = context.scene
        active = scene.ladar.sensor or scene.camera
        if active is not obj:
            col.label(text="Not the scene's active ladar sensor", icon="INFO")
        simulate_options(layout, scene)
        simulate_button(layout, obj.name)
        from ..core.warmup import is_warm

        if not is_warm():  # the first simulation would wait for the compiler: offer to do it now
            box = layout.box()
            box.label(text="Kernels not compiled yet on this computer", icon="INFO")
            box.operator("ladar.warm_up", text="Compile Kernels Now (about a minute, once)", icon="SCRIPTPLUGINS")
        row = layout.row(align=True)
        row.operator("ladar.export_config", text="Export Config", icon="EXPORT")
        row.operator("ladar.load_config", text="Load Config", icon="IMPORT")


class _SensorGroupPanel(_SensorPanel):
    bl_parent_id = "LADAR_PT_sensor"
    group = ""

    @classmethod
    def poll(cls, context):
        return super().poll(context) and group_used(context.object.ladar.system_type, cls.group)

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = getattr(context.object.ladar, self.group)
        self.draw_group(context, layout, props)

    def system_type(self, context):
        return context.object.ladar.system_type

    def draw_group(self, context, layout, props):
        draw_group_fields(layout, props, self.group, self.system_type(context))


class LADAR_PT_sensor_laser(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Laser"
    group = "laser"

    def draw_group(self, context, layout, props):
        kind = self.system_type(context)
        draw_group_fields(layout, props, "laser", kind, skip={"beam_divergence_rad"})
        row = layout.row()
        row.active = kind == "scanner" or not props.divergence_fills_fov
        row.prop(props, next(f.attr for f in SENSOR_FIELDS["laser"] if f.name == "beam_divergence_rad"))


class LADAR_PT_sensor_receiver(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Receiver"
    group = "receiver"

    def draw_group(self, context, layout, props):
        kind = self.system_type(context)
        draw_group_fields(layout, props, "receiver", kind)
        if kind == "profiler":
            layout.label(text="Range profiler: one detector element (pixel counts not used)", icon="INFO")
        elif kind == "scanner":
            layout.label(text="Scanner: the receiver collects the beam footprint", icon="INFO")


class LADAR_PT_sensor_gate(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Range Gate"
    group = "gate"

    def draw_group(self, context, layout, props):
        draw_group_fields(layout, props, "gate", self.system_type(context))
        g = si_values(props, "gate")
        start = 0.5 * SPEED_OF_LIGHT_M_S * g["gate_start_s"]
        per_bin = 0.5 * SPEED_OF_LIGHT_M_S * g["bin_width_s"]
        layout.label(text=f"Ranges {start:.4g} m … {start + per_bin * g['n_bins']:.4g} m, {per_bin:.3g} m per bin")


class LADAR_PT_sensor_scanner(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Scanner"
    group = "scanner"

    def draw_group(self, context, layout, props):
        layout.prop(props, "pattern")
        draw_group_fields(layout, props, "scanner", self.system_type(context), skip={"pattern"},
                          scan_pattern=props.pattern)
        rings = props.beam_subray_rings
        layout.label(text=f"{1 + 3 * rings * (rings + 1)} sub-rays per pulse", icon="INFO")
        if props.pattern == "rotating":
            box = layout.box()
            row = box.row()
            row.label(text="Channel Table")
            row.operator("ladar.channel_table_load", text="Load CSV", icon="FILEBROWSER")
            row.operator("ladar.channel_table_clear", text="", icon="X")
            try:
                lines = channel_table_lines(context.object)
            except Exception as exc:  # noqa: BLE001 - draw must never fail
                lines = [f"Error: {exc}"]
            for line in lines:
                box.label(text=line, icon="ERROR" if line.startswith("Error") else "NONE")


class LADAR_PT_sensor_gated(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Gated Viewing"
    group = "gated"

    def draw_group(self, context, layout, props):
        draw_group_fields(layout, props, "gated", self.system_type(context))
        g = si_values(props, "gated")
        spacing_m = 0.5 * SPEED_OF_LIGHT_M_S * g["delay_step_s"]
        depth_m = 0.5 * SPEED_OF_LIGHT_M_S * g["gate_width_s"]
        layout.label(text=f"Slice spacing {spacing_m:.4g} m, gate depth {depth_m:.4g} m", icon="INFO")


class LADAR_PT_sensor_detection(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Detection"
    bl_options = {"DEFAULT_CLOSED"}
    group = "detection"


class LADAR_PT_sensor_run(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Run"
    bl_options = {"DEFAULT_CLOSED"}
    group = "run"

    def draw_group(self, context, layout, props):
        scene_props = context.scene.ladar
        layout.prop(scene_props, "seed")
        draw_group_fields(layout, props, "run", self.system_type(context))
        layout.prop(scene_props, "output_dir")
        layout.prop(scene_props, "if_exists")


class LADAR_PT_sensor_detector(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Detector"
    bl_options = {"DEFAULT_CLOSED"}
    group = "detector"

    def draw_header_preset(self, context):
        draw_preset_header(self.layout, LADAR_MT_detector_presets, "ladar.detector_preset_add")

    def draw_group(self, context, layout, props):
        draw_group_fields(layout, props, "detector", self.system_type(context))
        layout.prop(context.scene.ladar, "reference_range_m")
        try:
            scene = context.scene
            cfg = sensor_config(scene, context.object)
            if cfg is None:
                lines = ["Derived figures unavailable: invalid sensor settings"]
            else:
                from ..ladar_addon import derived  # (at the first draw: it imports the simulator's physics)

                rng = reference_range_m(scene)
                fig = derived.atmosphere_figures(atmosphere_settings(scene), cfg.laser.wavelength_m, rng)
                lines = derived.detector_lines(cfg, rng, fig["two_way_transmission"])
        except Exception as exc:  # noqa: BLE001 - draw must never fail
            lines = [f"Derived figures unavailable: {exc}"]
        draw_lines(layout.box(), lines)


_KNOWN = {"laser", "receiver", "gate", "scanner", "gated", "detection", "detector", "run"}
#: Sub-panels for settings groups the core may add later (drawn generically, closed by default).
EXTRA_GROUP_PANELS = tuple(
    type(f"LADAR_PT_sensor_{group}", (_SensorGroupPanel, bpy.types.Panel),
         {"bl_label": group.replace("_", " ").title(), "group": group, "bl_options": {"DEFAULT_CLOSED"}})
    for group in SENSOR_FIELDS if group not in _KNOWN)

#: Every sensor panel, in drawing order.
SENSOR_PANELS = (LADAR_PT_sensor, LADAR_PT_sensor_laser, LADAR_PT_sensor_receiver, LADAR_PT_sensor_gate,
                 LADAR_PT_sensor_scanner, LADAR_PT_sensor_gated, LADAR_PT_sensor_detection,
                 LADAR_PT_sensor_detector, LADAR_PT_sensor_run, *EXTRA_GROUP_PANELS)

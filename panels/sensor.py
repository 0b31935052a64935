"""Ladar sensor panel in the Object Data tab of cameras, with one sub-panel per settings group."""
import math

import bpy

from ..ladar_addon import derived
from ..ladar_addon.presets import LADAR_MT_detector_presets, draw_preset_header
from ..ladar_addon.properties import SENSOR_FIELDS, TOP_FIELDS
from ..ladar_addon.sensor import camera_receiver_fov_rad
from .common import atmosphere_settings, draw_fields, draw_lines, reference_range_m, sensor_config, simulate_button


class _SensorPanel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "data"

    @classmethod
    def poll(cls, context):
        obj = context.object
        return obj is not None and obj.type == "CAMERA" and context.camera is not None


class LADAR_PT_sensor(_SensorPanel, bpy.types.Panel):
    bl_label = "Ladar Sensor"
    bl_idname = "LADAR_PT_sensor"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        obj = context.object
        for f in TOP_FIELDS:
            layout.prop(obj.ladar, f.attr)
        rx = obj.ladar.receiver
        col = layout.column(align=True)
        try:
            fov_x, fov_y = camera_receiver_fov_rad(obj.data, rx.width_px, rx.height_px)
            col.label(text=f"Field of view {math.degrees(fov_x):.4g}° × {math.degrees(fov_y):.4g}° "
                           f"(from the camera)", icon="CAMERA_DATA")
        except ValueError as exc:
            col.label(text=str(exc), icon="ERROR")
        scene = context.scene
        active = scene.ladar.sensor or scene.camera
        if active is not obj:
            col.label(text="Not the scene's active ladar sensor", icon="INFO")
        simulate_button(layout, obj.name)
        row = layout.row(align=True)
        row.operator("ladar.export_config", text="Export Config", icon="EXPORT")
        row.operator("ladar.load_config", text="Load Config", icon="IMPORT")


class _SensorGroupPanel(_SensorPanel):
    bl_parent_id = "LADAR_PT_sensor"
    group = ""

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = getattr(context.object.ladar, self.group)
        self.draw_group(context, layout, props)

    def draw_group(self, context, layout, props):
        draw_fields(layout, props, SENSOR_FIELDS[self.group])


class LADAR_PT_sensor_laser(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Laser"
    group = "laser"

    def draw_group(self, context, layout, props):
        draw_fields(layout, props, SENSOR_FIELDS["laser"], skip={"beam_divergence_rad"})
        row = layout.row()
        row.active = not props.divergence_fills_fov
        row.prop(props, "beam_divergence_rad")


class LADAR_PT_sensor_receiver(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Receiver"
    group = "receiver"


class LADAR_PT_sensor_gate(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Range Gate"
    group = "gate"

    def draw_group(self, context, layout, props):
        draw_fields(layout, props, SENSOR_FIELDS["gate"])
        c = 299_792_458.0
        start = 0.5 * c * props.gate_start_s
        end = start + 0.5 * c * props.bin_width_s * props.n_bins
        layout.label(text=f"Ranges {start:.4g} m … {end:.4g} m, {0.5 * c * props.bin_width_s:.3g} m per bin")


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
        draw_fields(layout, props, SENSOR_FIELDS["run"])
        layout.prop(scene_props, "output_dir")
        layout.prop(scene_props, "if_exists")


class LADAR_PT_sensor_detector(_SensorGroupPanel, bpy.types.Panel):
    bl_label = "Detector"
    bl_options = {"DEFAULT_CLOSED"}
    group = "detector"

    def draw_header_preset(self, context):
        draw_preset_header(self.layout, LADAR_MT_detector_presets, "ladar.detector_preset_add")

    def draw_group(self, context, layout, props):
        draw_fields(layout, props, SENSOR_FIELDS["detector"])
        layout.prop(context.scene.ladar, "reference_range_m")
        try:
            scene = context.scene
            cfg = sensor_config(scene, context.object)
            if cfg is None:
                lines = ["Derived figures unavailable: invalid sensor settings"]
            else:
                rng = reference_range_m(scene)
                fig = derived.atmosphere_figures(atmosphere_settings(scene), cfg.laser.wavelength_m, rng)
                lines = derived.detector_lines(cfg, rng, fig["two_way_transmission"])
        except Exception as exc:  # noqa: BLE001 - draw must never fail
            lines = [f"Derived figures unavailable: {exc}"]
        draw_lines(layout.box(), lines)


_KNOWN = {"laser", "receiver", "gate", "detection", "detector", "run"}
#: Sub-panels for settings groups the core may add later (drawn generically, closed by default).
EXTRA_GROUP_PANELS = tuple(
    type(f"LADAR_PT_sensor_{group}", (_SensorGroupPanel, bpy.types.Panel),
         {"bl_label": group.replace("_", " ").title(), "group": group, "bl_options": {"DEFAULT_CLOSED"}})
    for group in SENSOR_FIELDS if group not in _KNOWN)
